//! The single-sway fit of a sensor's window, kept up to date as the window slides, so that a
//! window near its limit costs what its batch carries rather than a search over the whole
//! window on every batch (the fleet bench: a search per batch judged 0.35 M samples/s a core).
//!
//! Per swaying axis the tracker holds the window's [`Moments`] at one ω, the ω the last search
//! converged to: each sample that enters the window is added, each that leaves is taken away
//! (and so are the runs of five consecutive samples behind the fourth differences). At a fixed
//! ω those moments are the whole least-squares fit ([`sinefit::fit_at`]): the window is judged
//! on every batch with the same fit, the same uncertainties and the same adequacy tests as a
//! window fitted afresh, at that ω. Each judgement also gives the Gauss–Newton step from ω to
//! the window's own optimum; the reported frequency is ω + step, and when the step exceeds
//! [`RETUNE_OMEGA_U`] standard uncertainties of ω (or the fit at ω is not adequate) ω is
//! searched again by Gauss–Newton steps over the window and the moments are rebuilt there.
//! At half a standard uncertainty from the optimum, the amplitude differs from the optimum's
//! by a relative `≈ s²/(8·A²·n)` (second order: the amplitude does not depend on ω to first
//! order there), far below its u.
//!
//! The tracker speaks only for windows whose every sample is clean and usable and for sensors
//! without a frequency limit; everything else, and any axis that can reach a limit without an
//! adequate fit, is judged in full by [`crate::stats::window_stats`].

use std::collections::VecDeque;

use super::TimedSample;
use crate::sinefit::{self, Geometry, Moments, SineFit};
use crate::stats::{self, AxisSummary, Point, Request, WindowStats};

/// How far ω may be from the window's optimum, in its standard uncertainties, before it is
/// searched again.
pub(super) const RETUNE_OMEGA_U: f64 = 0.5;

/// Batches to wait after a window could not be tracked (no adequate sway on an axis that
/// matters) before trying again: each try is a search over the window.
const ARM_BACKOFF_BATCHES: u32 = 10;

/// Gauss–Newton steps of a retune; from within a few u of the optimum two are plenty.
const RETUNE_STEPS: usize = 2;

#[derive(Debug, Clone)]
struct AxisTrack {
    /// rad per sample.
    omega: f64,
    /// Sample index of τ = 0 (the window's first sample when the moments were built).
    origin: i64,
    /// N of τ = (m − origin)/N.
    scale: f64,
    moments: Moments,
}

#[derive(Debug, Default)]
pub(super) struct SwayTracker {
    armed: bool,
    axes: [Option<AxisTrack>; 3],
    /// Samples in the window that are not clean and usable.
    unclean: usize,
    backoff: u32,
    /// Time of sample index 0, and the sample period: a sample's index is its time on that
    /// grid.
    epoch_ns: Option<i64>,
    period_ns: f64,
}

fn clean(s: &TimedSample) -> bool {
    s.usable && s.flags == 0
}

impl SwayTracker {
    fn index(&self, t_ns: i64) -> i64 {
        let epoch = self.epoch_ns.unwrap_or(t_ns);
        ((t_ns - epoch) as f64 / self.period_ns).round() as i64
    }

    /// Stops tracking: the window is judged in full until the tracker is armed again.
    pub(super) fn disarm(&mut self) {
        self.armed = false;
        self.axes = [None, None, None];
    }

    /// Whether the five samples ending at `last` (an index into `window`) are consecutive.
    fn run_ending_at(&self, window: &VecDeque<TimedSample>, last: usize) -> Option<[usize; 5]> {
        let first = last.checked_sub(4)?;
        let at = |i: usize| self.index(window[i].t_ns);
        (at(last) - at(first) == 4).then(|| [first, first + 1, first + 2, first + 3, last])
    }

    fn add(
        &mut self,
        sign: f64,
        window: &VecDeque<TimedSample>,
        at: usize,
        run: Option<[usize; 5]>,
    ) {
        let m = self.index(window[at].t_ns);
        let run_mid = run.map(|r| (self.index(window[r[2]].t_ns), r));
        for (j, track) in self.axes.iter_mut().enumerate() {
            let Some(track) = track else { continue };
            let (sin, cos) = (track.omega * (m - track.origin) as f64).sin_cos();
            let tau = (m - track.origin) as f64 / track.scale;
            let y = f64::from(window[at].accel_mps2[j]);
            track.moments.sample(sign, tau, cos, sin, y);
            if let Some((mid, r)) = run_mid {
                let (sin, cos) = (track.omega * (mid - track.origin) as f64).sin_cos();
                let d = sinefit::fourth_difference(r.map(|i| f64::from(window[i].accel_mps2[j])));
                track.moments.run(sign, d, cos, sin);
            }
        }
    }

    /// The window's newest sample was pushed.
    pub(super) fn on_push(&mut self, window: &VecDeque<TimedSample>, period_ns: f64) {
        let Some(newest) = window.back() else { return };
        if window.len() == 1 || self.epoch_ns.is_none() {
            *self = SwayTracker {
                epoch_ns: Some(newest.t_ns),
                period_ns,
                ..SwayTracker::default()
            };
        }
        if !clean(newest) {
            self.unclean += 1;
            self.disarm();
            return;
        }
        if self.armed {
            let last = window.len() - 1;
            let run = self.run_ending_at(window, last);
            self.add(1.0, window, last, run);
        }
    }

    /// The window's oldest sample is about to leave it.
    pub(super) fn on_pop(&mut self, window: &VecDeque<TimedSample>) {
        let Some(oldest) = window.front() else { return };
        if !clean(oldest) {
            self.unclean = self.unclean.saturating_sub(1);
            return;
        }
        if self.armed {
            let run = (window.len() >= 5)
                .then(|| self.run_ending_at(window, 4))
                .flatten();
            self.add(-1.0, window, 0, run);
        }
    }

    /// The moments of axis `j` over the window at ω after up to `steps` Gauss–Newton steps
    /// from `omega`, origin at the window's first sample; None when the steps diverge.
    fn build(
        &self,
        window: &VecDeque<TimedSample>,
        j: usize,
        omega: f64,
        steps: usize,
        geometry: &Geometry,
        noise_bound: f64,
    ) -> Option<AxisTrack> {
        let origin = self.index(window.front()?.t_ns);
        let index: Vec<u32> = window
            .iter()
            .map(|s| (self.index(s.t_ns) - origin) as u32)
            .collect();
        let value: Vec<f64> = window.iter().map(|s| f64::from(s.accel_mps2[j])).collect();
        let axis = sinefit::Axis {
            index: &index,
            value: &value,
            grid_len: geometry.grid_len,
        };
        // Two bins of the window's length either side: the search's own bracket.
        let bracket = 2.0 * std::f64::consts::TAU / f64::from(geometry.grid_len.max(1));
        let at_origin = Geometry {
            grid_start: 0.0,
            scale: f64::from(geometry.grid_len.max(1)),
            ..*geometry
        };
        let omega = sinefit::newton(
            omega,
            bracket,
            steps,
            |w| axis.moments(w, false),
            &at_origin,
            noise_bound,
        )?;
        Some(AxisTrack {
            omega,
            origin,
            scale: at_origin.scale,
            moments: axis.moments(omega, true),
        })
    }

    /// Arms the tracker on the window: a full search per axis.
    fn arm(&mut self, window: &VecDeque<TimedSample>, request: &Request) {
        let Some(first) = window.front() else { return };
        let first_index = self.index(first.t_ns);
        let points: Vec<Point> = window
            .iter()
            .map(|t| Point {
                index: (self.index(t.t_ns) - first_index) as u32,
                accel_mps2: t.accel_mps2,
                vibration_mps2: t.vibration,
                uncertainty_mps2: t.uncertainty_mps2,
            })
            .collect();
        let geometry = Geometry {
            rate_hz: request.sample_rate_hz,
            scale: f64::from(request.grid_len.max(1)),
            grid_start: 0.0,
            grid_len: request.grid_len,
            largest: 0.0,
            highpass: request.highpass,
        };
        let omegas = stats::sway_frequencies(&points, request);
        for (j, omega) in omegas.into_iter().enumerate() {
            self.axes[j] = omega.and_then(|w| self.build(window, j, w, 0, &geometry, 0.0));
        }
        self.armed = true;
    }

    /// The fit of axis `j` for the window as it is, retuned if ω has moved; None when the axis
    /// is not tracked or has no adequate fit.
    fn fit(
        &mut self,
        window: &VecDeque<TimedSample>,
        j: usize,
        summary: &AxisSummary,
        request: &Request,
    ) -> Option<SineFit> {
        let front = self.index(window.front()?.t_ns);
        let geometry = |track: &AxisTrack| Geometry {
            rate_hz: request.sample_rate_hz,
            scale: track.scale,
            grid_start: (front - track.origin) as f64,
            grid_len: request.grid_len,
            largest: summary.largest_accel,
            highpass: request.highpass,
        };
        let track = self.axes[j].as_ref()?;
        // The origin trails the window as it slides: rebuilt once it is a window behind, so
        // that τ stays within [0, 2] and the sums' rounding does not build up.
        let stale = (front - track.origin) as f64 > track.scale;
        let at = sinefit::fit_at(
            &track.moments,
            track.omega,
            &geometry(track),
            summary.mean_u,
        );
        // Close enough: within RETUNE_OMEGA_U of ω's u, or drifting less than 10⁻⁴ rad over
        // the window (a relative error of the amplitude below 10⁻⁹; an exact sinusoid has a u
        // of ω at the rounding of its samples).
        let close = |a: &sinefit::AtOmega| {
            a.step.abs() <= (RETUNE_OMEGA_U * a.omega_u).max(1e-4 / track.scale)
        };
        if let Some(at) = at {
            if !stale && at.fit.is_some() && close(&at) {
                return at.fit;
            }
        }
        let start = track.omega + at.map_or(0.0, |a| a.step).clamp(-0.1, 0.1);
        let steps = if stale && at.is_some_and(|a| close(&a)) {
            0
        } else {
            RETUNE_STEPS
        };
        let rebuilt = self.build(window, j, start, steps, &geometry(track), summary.mean_u);
        self.axes[j] = rebuilt;
        let track = self.axes[j].as_ref()?;
        sinefit::fit_at(
            &track.moments,
            track.omega,
            &geometry(track),
            summary.mean_u,
        )?
        .fit
    }

    /// Peak and RMS of the window from the tracked fits (see the module documentation); None
    /// when the window must be judged in full.
    pub(super) fn stats(
        &mut self,
        window: &VecDeque<TimedSample>,
        summaries: &[AxisSummary; 3],
        request: &Request,
    ) -> Option<WindowStats> {
        if self.unclean > 0 || request.frequency {
            self.disarm();
            return None;
        }
        if !self.armed {
            if self.backoff > 0 {
                self.backoff -= 1;
                return None;
            }
            self.arm(window, request);
        }
        let found = stats::stats_from_fits(summaries, window.len(), request, |j| {
            self.fit(window, j, &summaries[j], request)
        });
        if found.is_none() {
            self.disarm();
            self.backoff = ARM_BACKOFF_BATCHES;
        }
        found
    }
}

#[cfg(test)]
mod tests {
    use super::super::*;
    use rand::{Rng, SeedableRng};
    use rand_distr::{Distribution, Normal};
    use triax_protocol::{BatchHeader, CorrectionInfo, Mode};

    /// A sway near its limit whose frequency drifts, in white noise, in 10-sample batches: on
    /// every batch the tracked fit gives the peak a search over the window gives, to a small
    /// share of its u, and it is tracked (not judged in full) on almost every batch.
    #[test]
    fn the_tracked_fit_is_the_searched_one() {
        let config = Config::from_toml(
            "window_s = 4.0\nstale_after_s = 1e9\nrepeat_interval_s = 0.0\nhighpass_hz = 0.3\n\
             noise_share = 1.0\n[buildings.hq.sensors.s]\npga_mps2 = 0.968\n",
        )
        .expect("valid");
        let t0 = OffsetDateTime::from_unix_timestamp(1_800_000_000).expect("in range");
        let mut m = Monitor::new(config, t0);
        let hq = BuildingId::new("hq").expect("id");
        let mut rng = rand::rngs::StdRng::seed_from_u64(5);
        let noise = Normal::new(0.0, 0.01).expect("finite");
        let (rate, batch) = (100.0, 10usize);
        let mut phase = rng.gen_range(0.0..std::f64::consts::TAU);
        let (mut compared, mut worst_in_u) = (0, 0.0f64);
        for seq in 0..3000u64 {
            let samples = (0..batch)
                .map(|i| {
                    let t = (seq as usize * batch + i) as f64 / rate;
                    // 1.3 Hz drifting by ±2 % over the run.
                    let f = 1.3 * (1.0 + 0.02 * (t / 30.0).sin());
                    phase += std::f64::consts::TAU * f / rate;
                    let x = 0.3 + 0.97 * phase.sin() + noise.sample(&mut rng);
                    CorrectedSample {
                        accel_mps2: [x as f32, noise.sample(&mut rng) as f32, 9.81],
                        uncertainty_mps2: [0.01; 3],
                        flags: 0,
                    }
                })
                .collect();
            let b = CorrectedBatch {
                header: BatchHeader {
                    sensor_id: SensorId::new("s").expect("id"),
                    sequence: seq,
                    timestamp_ns: 1_800_000_000_000_000_000 + seq as i64 * 100_000_000,
                    sample_rate_hz: rate,
                },
                batch_flags: 0,
                info: CorrectionInfo {
                    calibration_version: 1,
                    mode: Mode::Dynamic,
                    coverage_factor: 2.0,
                },
                samples,
            };
            let now = t0 + time::Duration::milliseconds(seq as i64 * 100);
            let alerts = m.on_corrected(&hq, &b, now);
            let Some(tracked) = alerts
                .iter()
                .find(|a| a.kind == AlertKind::PeakAcceleration)
            else {
                continue;
            };
            let key = (hq.clone(), SensorId::new("s").expect("id"));
            let state = m.sensors.get_mut(&key).expect("watched");
            if !state.sway.armed {
                continue;
            }
            // The same window, searched afresh.
            let first = state.window.front().expect("a window").t_ns;
            let points: Vec<Point> = state
                .window
                .iter()
                .map(|t| Point {
                    index: ((t.t_ns - first) as f64 / 1e7).round() as u32,
                    accel_mps2: t.accel_mps2,
                    vibration_mps2: t.vibration,
                    uncertainty_mps2: t.uncertainty_mps2,
                })
                .collect();
            let request = Request {
                sample_rate_hz: rate,
                grid_len: points.len() as u32,
                propagation: crate::stats::Propagation { noise_share: 1.0 },
                k: 2.0,
                peak_threshold: Some(0.968),
                rms_threshold: None,
                frequency: false,
                highpass: state.highpass.as_ref().map(HighPass::response),
            };
            let searched = window_stats(&points, &request)
                .and_then(|s| s.peak)
                .expect("a peak");
            assert!(matches!(searched.method, Method::Sine { .. }));
            let u = searched.estimate.standard_uncertainty;
            worst_in_u = worst_in_u.max((tracked.value - searched.estimate.value).abs() / u);
            assert!(
                (tracked.standard_uncertainty / u - 1.0).abs() < 0.01,
                "{tracked:?} against {searched:?}"
            );
            compared += 1;
        }
        println!("{compared} batches compared, worst difference {worst_in_u:.4} u");
        assert!(compared > 1000, "{compared}");
        assert!(worst_in_u < 0.05, "{worst_in_u}");
    }
}
