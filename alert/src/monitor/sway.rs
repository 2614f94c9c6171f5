//! The single-sway fit of a sensor's window, kept up to date as the window slides, so that a
//! window near its limit costs what its batch carries rather than a search over the whole
//! window on every batch (the fleet bench: a search per batch judged 0.35 M samples/s a core).
//!
//! Per swaying axis the tracker holds the window's [`Moments`] at one ω, the ω the last search
//! converged to: each sample that enters the window is added, each that leaves is taken away
//! (and so are the runs of five consecutive samples behind the fourth differences). At a fixed
//! ω those moments are the whole least-squares fit ([`sinefit::fit_at`]), and they also carry
//! it to the window's own optimum: the Gauss–Newton step from ω gives the optimum's frequency
//! ω + step, and the sinusoid is carried there to first order in the step (its derivative in ω
//! comes from the same sums). So every batch is judged with the fit, the uncertainties and the
//! adequacy tests of a window fitted afresh, to second order in the step. When what is left of
//! the second order could exceed [`RETUNE_PEAK_U`] of the amplitude's u, ω is searched again by
//! Gauss–Newton steps over the window and the moments are rebuilt there. Once their origin is a
//! window behind the window's start, it is moved to the start by a linear map of the moments
//! ([`Moments::moved`]) while ω is close to the optimum, and otherwise (and every few moves)
//! they are rebuilt at ω + step. A window whose tracked fit is not adequate is judged in full,
//! and its sums are kept up to date for the next.
//!
//! The tracker speaks only for windows whose every sample is clean and usable and for sensors
//! without a frequency limit; everything else, and any axis that can reach a limit without an
//! adequate fit, is judged in full by [`crate::stats::window_stats`].

use std::collections::VecDeque;

use super::TimedSample;
use crate::sinefit::{self, Geometry, Moments, SineFit};
use crate::stats::{self, AxisSummary, Point, Request, WindowStats};

/// How far the tracked fit may be from the window's optimum's, in the amplitude's standard
/// uncertainties, before ω is searched again: a bound on what the fit carried from ω to the
/// optimum leaves of the second order in the step ([`sinefit::AtOmega::carry_error_u`]). It
/// grows as the square of the step in u(ω) and as u(ω)·N (the phase the window turns by over
/// one u(ω), larger the weaker the sway), so no one number of u(ω) suits every sway: this
/// allows about 6 u(ω) to a sway 100 times its noise over 400 samples, 2 u(ω) to one 10 times
/// its noise. The test `the_tracked_fit_is_the_searched_one` finds 0.7 of it at most.
pub(super) const RETUNE_PEAK_U: f64 = 0.02;

/// Batches to wait after a window could not be tracked (an axis that matters had no sway to
/// track) before trying again: each try is a search over the window.
const ARM_BACKOFF_BATCHES: u32 = 10;

/// Gauss–Newton steps of a retune; from within a few u of the optimum two are plenty.
const RETUNE_STEPS: usize = 2;

/// Moves of the sums' origin by their own map ([`Moments::moved`]) before they are rebuilt
/// from the window: each move and each sample in and out adds rounding of about 1e-16 of the
/// sums, far below anything the fit resolves after this many windows.
const MOVES: u32 = 16;

/// (cos, sin) of ω·k at the last k asked for at one end of the window.
#[derive(Debug, Clone, Copy)]
struct Phase {
    k: i64,
    cos: f64,
    sin: f64,
    /// Rotations since the last exact value.
    turns: u32,
}

/// Rotations before a phase is computed exactly again: each adds about 1e-16 of rounding, far
/// below anything the fit resolves even after this many.
const EXACT_EVERY: u32 = 1024;

/// The phases of one ω at the window's two ends. Samples enter and leave the window in order,
/// so each end's next phase is its last turned by ω: four products where `sin_cos` was a tenth
/// of the service's time near the limit (perf, 10 × 100 sensors).
#[derive(Debug, Clone)]
struct Phases {
    /// (cos ω, sin ω) and (cos 2ω, sin 2ω).
    turn: (f64, f64),
    turn2: (f64, f64),
    entering: Option<Phase>,
    leaving: Option<Phase>,
}

impl Phases {
    fn new(omega: f64) -> Phases {
        let (s1, c1) = omega.sin_cos();
        let (s2, c2) = (2.0 * omega).sin_cos();
        Phases {
            turn: (c1, s1),
            turn2: (c2, s2),
            entering: None,
            leaving: None,
        }
    }

    /// (cos, sin) of ω·k at the entering (`entering`) or leaving end.
    fn at(&mut self, entering: bool, k: i64, omega: f64) -> (f64, f64) {
        let (c1, s1) = self.turn;
        let end = if entering {
            &mut self.entering
        } else {
            &mut self.leaving
        };
        let next = match *end {
            Some(p) if p.k + 1 == k && p.turns < EXACT_EVERY => Phase {
                k,
                cos: p.cos * c1 - p.sin * s1,
                sin: p.sin * c1 + p.cos * s1,
                turns: p.turns + 1,
            },
            _ => {
                let (sin, cos) = (omega * k as f64).sin_cos();
                Phase {
                    k,
                    cos,
                    sin,
                    turns: 0,
                }
            }
        };
        *end = Some(next);
        (next.cos, next.sin)
    }

    /// (cos, sin) of ω·(k + by) from those at k, for `by` = ±2 (the middle of a run of five
    /// consecutive samples at either end); other offsets are computed.
    fn offset(&self, (cos, sin): (f64, f64), k: i64, by: i64, omega: f64) -> (f64, f64) {
        let (c2, s2) = self.turn2;
        match by {
            2 => (cos * c2 - sin * s2, sin * c2 + cos * s2),
            -2 => (cos * c2 + sin * s2, sin * c2 - cos * s2),
            _ => {
                let (sin, cos) = (omega * (k + by) as f64).sin_cos();
                (cos, sin)
            }
        }
    }
}

#[derive(Debug, Clone)]
struct AxisTrack {
    /// rad per sample.
    omega: f64,
    phases: Phases,
    /// Sample index of τ = 0 (the window's first sample when the moments were built).
    origin: i64,
    /// N of τ = (m − origin)/N.
    scale: f64,
    moments: Moments,
    /// Times the origin was moved by the sums' own map since they were built.
    moves: u32,
}

#[derive(Debug)]
pub(super) struct SwayTracker {
    /// [`RETUNE_PEAK_U`]; a field so that a test can measure what other values do.
    retune_peak_u: f64,
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

impl Default for SwayTracker {
    fn default() -> Self {
        SwayTracker {
            retune_peak_u: RETUNE_PEAK_U,
            armed: false,
            axes: [None, None, None],
            unclean: 0,
            backoff: 0,
            epoch_ns: None,
            period_ns: 0.0,
        }
    }
}

fn clean(s: &TimedSample) -> bool {
    s.usable && !super::flagged(s.flags)
}

impl SwayTracker {
    fn index(&self, t_ns: i64) -> i64 {
        let epoch = self.epoch_ns.unwrap_or(t_ns);
        let x = (t_ns - epoch) as f64 / self.period_ns;
        // Rounded half away from zero, as `f64::round`, without its call into libm (a few %
        // of the tracker, which asks for three indices a sample).
        if x >= 0.0 {
            (x + 0.5) as i64
        } else {
            -((0.5 - x) as i64)
        }
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
        let entering = sign > 0.0;
        for (j, track) in self.axes.iter_mut().enumerate() {
            let Some(track) = track else { continue };
            let k = m - track.origin;
            let (cos, sin) = track.phases.at(entering, k, track.omega);
            let tau = k as f64 / track.scale;
            let y = f64::from(window[at].accel_mps2[j]);
            track.moments.sample(sign, tau, cos, sin, y);
            if let Some((mid, r)) = run_mid {
                let (cos, sin) = track.phases.offset((cos, sin), k, mid - m, track.omega);
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
                retune_peak_u: self.retune_peak_u,
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
            phases: Phases::new(omega),
            origin,
            scale: at_origin.scale,
            moments: axis.moments(omega, true),
            moves: 0,
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
    /// is not tracked (then `axes[j]` is None) or its fit is not adequate.
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
        // Close enough: the fit carried to the optimum is off by at most RETUNE_PEAK_U of its
        // u, or ω drifts by less than 10⁻⁴ rad over the window (an exact sinusoid has a u(ω) at
        // the rounding of its samples).
        let close = |a: &sinefit::AtOmega| {
            a.carry_error_u <= self.retune_peak_u
                || a.step.abs() * f64::from(request.grid_len) <= 1e-4
        };
        if let Some(at) = at {
            // Carried to the optimum, the fit is the optimum's, adequate or not: a search
            // would come to the same verdict.
            if !stale && close(&at) {
                return at.fit;
            }
            // A window behind, with ω well within reach of the optimum (a quarter of the step
            // that would retune), the origin moves by the sums' own map rather than a pass
            // over the window; the fit does not depend on where τ = 0 is. Every so often they
            // are rebuilt anyway, recentred at the optimum, so that the rounding of samples
            // added and taken away does not build up.
            if stale && at.carry_error_u <= self.retune_peak_u / 16.0 && track.moves < MOVES {
                let shift = front - track.origin;
                if let Some(track) = self.axes[j].as_mut() {
                    track.moments = track
                        .moments
                        .moved(track.omega * shift as f64, shift as f64 / track.scale);
                    track.origin = front;
                    track.moves += 1;
                    // The ends' phases were of the old origin.
                    track.phases = Phases::new(track.omega);
                }
                return at.fit;
            }
        }
        let start = track.omega + at.map_or(0.0, |a| a.step).clamp(-0.1, 0.1);
        let steps = if at.is_some_and(|a| close(&a)) {
            0
        } else {
            RETUNE_STEPS
        };
        let rebuilt = self.build(window, j, start, steps, &geometry(track), summary.mean_u);
        self.axes[j] = rebuilt;
        let track = self.axes[j].as_ref()?;
        let at = sinefit::fit_at(
            &track.moments,
            track.omega,
            &geometry(track),
            summary.mean_u,
        );
        if at.is_none() {
            // Singular where the search ended: nothing to track.
            self.axes[j] = None;
        }
        at?.fit
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
        let mut untracked = false;
        let found = stats::stats_from_fits(summaries, window.len(), request, |j| {
            let fit = self.fit(window, j, &summaries[j], request);
            untracked |= self.axes[j].is_none();
            fit
        });
        // A tracked axis whose fit is not adequate for now is judged in full for now, and kept
        // up to date: its sums are still the window's. One that is not tracked needs a search.
        if found.is_none() && untracked {
            self.disarm();
            self.backoff = ARM_BACKOFF_BATCHES;
        }
        found
    }
}

#[cfg(test)]
mod tests {
    use super::super::*;
    use super::{Phases, RETUNE_PEAK_U};
    use crate::sinefit::{self, Geometry};
    use rand::{Rng, SeedableRng};
    use rand_distr::{Distribution, Normal};

    #[test]
    fn rotated_phases_are_the_computed_ones() {
        let omega = std::f64::consts::TAU * 1.3 / 100.0 + 1e-3;
        let mut phases = Phases::new(omega);
        let exact = |k: i64| {
            let (s, c) = (omega * k as f64).sin_cos();
            (c, s)
        };
        let mut worst = 0.0f64;
        // Both ends walk on in order, with a jump (a sample missing) and a start again below.
        let ks = (0..5_000).chain(7_000..9_000).chain(100..200);
        for (n, k) in ks.enumerate() {
            let (c, s) = phases.at(true, k, omega);
            let (c0, s0) = exact(k);
            worst = worst.max((c - c0).abs()).max((s - s0).abs());
            let leaving = k - 1_000;
            let (lc, ls) = phases.at(false, leaving, omega);
            let (lc0, ls0) = exact(leaving);
            worst = worst.max((lc - lc0).abs()).max((ls - ls0).abs());
            for by in [-2, 2, 3] {
                let (oc, os) = phases.offset((c, s), k, by, omega);
                let (oc0, os0) = exact(k + by);
                assert!(
                    (oc - oc0).abs() < 1e-12 && (os - os0).abs() < 1e-12,
                    "step {n}: k {k} offset by {by}"
                );
            }
        }
        assert!(worst < 1e-12, "worst difference {worst}");
    }

    /// A 100 Hz batch of `sensor` numbered `seq` (its first sample 0.1·seq s after the epoch).
    fn corrected(sensor: &str, seq: u64, samples: Vec<CorrectedSample>) -> CorrectedBatch {
        triax_protocol::batch::sample::dynamic(
            SensorId::new(sensor).expect("id"),
            seq,
            1_800_000_000_000_000_000 + (seq * samples.len() as u64) as i64 * 10_000_000,
            100.0,
            samples,
        )
    }

    /// How a tracker with a given retune threshold compares with a fresh search.
    struct Compared {
        /// Batches whose tracked peak was compared with a search's.
        batches: usize,
        /// Largest |tracked − searched| peak, in the searched peak's u.
        worst_in_u: f64,
        /// Largest |1 − tracked u / searched u|.
        worst_u_ratio: f64,
        /// Batches on which the tracked sums were rebuilt.
        rebuilds: usize,
        /// Batches whose window was not one sway, by both fits.
        inadequate: usize,
    }

    /// A sway of amplitude `sway` near its limit whose frequency drifts, in white noise of 0.01
    /// (`seed`), 3 000 batches of 10 samples into a 4 s window, with ω searched again beyond
    /// `retune_peak_u`: every batch's tracked peak against a search over the same window.
    fn tracked_against_searched(retune_peak_u: f64, seed: u64, sway: f64) -> Compared {
        // The limit at about the peak of the sway above the baseline.
        let limit = 0.968 / 0.97 * sway;
        let config = Config::from_toml(&format!(
            "window_s = 4.0\nstale_after_s = 1e9\nrepeat_interval_s = 0.0\nhighpass_hz = 0.3\n\
             noise_share = 1.0\n[buildings.hq.sensors.s]\npga_mps2 = {limit}\n",
        ))
        .expect("valid");
        let t0 = OffsetDateTime::from_unix_timestamp(1_800_000_000).expect("in range");
        let mut m = Monitor::new(config, t0);
        let hq = BuildingId::new("hq").expect("id");
        let key = (hq.clone(), SensorId::new("s").expect("id"));
        let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
        let noise = Normal::new(0.0, 0.01).expect("finite");
        let (rate, batch) = (100.0, 10usize);
        let mut phase = rng.gen_range(0.0..std::f64::consts::TAU);
        let mut compared = Compared {
            batches: 0,
            worst_in_u: 0.0,
            worst_u_ratio: 0.0,
            rebuilds: 0,
            inadequate: 0,
        };
        for seq in 0..3000u64 {
            let samples = (0..batch)
                .map(|i| {
                    let t = (seq as usize * batch + i) as f64 / rate;
                    // 1.3 Hz drifting by ±2 % over the run.
                    let f = 1.3 * (1.0 + 0.02 * (t / 30.0).sin());
                    phase += std::f64::consts::TAU * f / rate;
                    let x = 0.3 + sway * phase.sin() + noise.sample(&mut rng);
                    CorrectedSample {
                        accel_mps2: [x as f32, noise.sample(&mut rng) as f32, 9.81],
                        uncertainty_mps2: [0.01; 3],
                        flags: 0,
                    }
                })
                .collect();
            let b = corrected("s", seq, samples);
            let now = t0 + time::Duration::milliseconds(seq as i64 * 100);
            let origin = |m: &Monitor| {
                m.sensors
                    .get(&key)
                    .and_then(|s| s.sway.axes[0].as_ref().map(|t| t.origin))
            };
            let before = origin(&m);
            let alerts = m.on_corrected(&hq, &b, now);
            let state = m.sensors.get_mut(&key).expect("watched");
            state.sway.retune_peak_u = retune_peak_u;
            let Some(tracked) = alerts
                .iter()
                .find(|a| a.kind == AlertKind::PeakAcceleration)
            else {
                continue;
            };
            if !state.sway.armed {
                continue;
            }
            // Every build starts the sums at the window's first sample, which moves each batch.
            let after = state.sway.axes[0].as_ref().map(|t| t.origin);
            compared.rebuilds += usize::from(before.is_some() && after != before);
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
                peak_threshold: Some(limit),
                rms_threshold: None,
                frequency: false,
                highpass: state.highpass.as_ref().map(HighPass::response),
            };
            let searched = window_stats(&points, &request)
                .and_then(|s| s.peak)
                .expect("a peak");
            // A window whose tracked fit is not adequate is judged in full, so the peak is the
            // search's whenever either fit is not adequate; the verdicts must agree.
            let fitted = tracked.statement.contains("one sway");
            assert_eq!(
                fitted,
                matches!(searched.method, Method::Sine { .. }),
                "{tracked:?} against {searched:?}"
            );
            compared.inadequate += usize::from(!fitted);
            let u = searched.estimate.standard_uncertainty;
            compared.worst_in_u = compared
                .worst_in_u
                .max((tracked.value - searched.estimate.value).abs() / u);
            compared.worst_u_ratio = compared
                .worst_u_ratio
                .max((tracked.standard_uncertainty / u - 1.0).abs());
            compared.batches += 1;
        }
        compared
    }

    /// On every batch the tracked fit gives the peak a search over the window gives, to a small
    /// share of its u, for a strong sway (its amplitude 100 times the noise) and a weak one
    /// (10 times), with the same verdict on whether the window is one sway.
    #[test]
    fn the_tracked_fit_is_the_searched_one() {
        for sway in [0.97, 0.1] {
            let c = tracked_against_searched(RETUNE_PEAK_U, 5, sway);
            println!(
                "sway {sway}: {} batches compared ({} not one sway), worst difference {:.4} u, \
                 u within {:.2e}, {} rebuilds",
                c.batches, c.inadequate, c.worst_in_u, c.worst_u_ratio, c.rebuilds
            );
            assert!(c.batches > 2000, "{}", c.batches);
            assert!(c.worst_in_u < 0.02, "{}", c.worst_in_u);
            assert!(c.worst_u_ratio < 0.01, "{}", c.worst_u_ratio);
        }
    }

    /// The tracked peak's worst difference from a search, and the rebuilds, by retune
    /// threshold and sway, over five seeds.
    /// `cargo test --release -p triax-alert --lib -- --ignored retune_thresholds --nocapture`
    #[test]
    #[ignore = "a measurement: prints, asserts nothing"]
    fn retune_thresholds() {
        println!(
            "| threshold (u) | sway (m/s²) | worst difference (u), per seed | rebuilds a batch |"
        );
        for threshold in [0.005, 0.01, 0.02, 0.03, 0.04, 0.06] {
            for sway in [0.97, 0.3, 0.1] {
                let runs: Vec<Compared> = (5..10)
                    .map(|seed| tracked_against_searched(threshold, seed, sway))
                    .collect();
                let worst: Vec<String> = runs
                    .iter()
                    .map(|c| format!("{:.4}", c.worst_in_u))
                    .collect();
                let rebuilds = runs.iter().map(|c| c.rebuilds).sum::<usize>() as f64
                    / runs.iter().map(|c| c.batches).sum::<usize>() as f64;
                println!(
                    "| {threshold} | {sway} | {} | {rebuilds:.3} |",
                    worst.join(", ")
                );
            }
        }
    }

    /// The cost of windows near their limit, as the fleet bench's `--sway-mps2 1.9` loads the
    /// service: 100 sensors at 100 Hz swaying at 1.3 Hz with 1.9 m/s² against a 2 m/s² PGA
    /// limit, white noise of 0.01 m/s² (the stated u) on every axis, 10-sample batches, a 10 s
    /// window and a 1 Hz baseline. Prints the time per sample of the judged batches and how
    /// often the tracker rebuilt its sums: re-searched ω (a retune), moved the origin only, or
    /// armed with a full search.
    /// `cargo test --release -p triax-alert --lib -- --ignored cost_near_the_limit --nocapture`
    #[test]
    #[ignore = "a measurement: prints, asserts nothing"]
    fn cost_near_the_limit() {
        for batch_samples in [10u64, 100] {
            cost_near_the_limit_in(batch_samples);
        }
    }

    fn cost_near_the_limit_in(batch_samples: u64) {
        let config = Config::from_toml(
            "window_s = 10.0\nstale_after_s = 1e9\nrepeat_interval_s = 0.0\nhighpass_hz = 1.0\n\
             [defaults]\npga_mps2 = 2.0\n[buildings.hq]\n",
        )
        .expect("valid");
        let t0 = OffsetDateTime::from_unix_timestamp(1_800_000_000).expect("in range");
        let mut m = Monitor::new(config, t0);
        let hq = BuildingId::new("hq").expect("id");
        let mut rng = rand::rngs::StdRng::seed_from_u64(1);
        let noise = Normal::new(0.0, 0.01).expect("finite");
        let (sensors, seconds, warm_up) = (100, 120u64, 12u64);
        let names: Vec<String> = (0..sensors).map(|s| format!("s{s:03}")).collect();
        let keys: Vec<_> = names
            .iter()
            .map(|s| (hq.clone(), SensorId::new(s).expect("id")))
            .collect();
        let tracks = |m: &Monitor, key| match m.sensors.get(key) {
            Some(state) => (
                state.sway.armed,
                state
                    .sway
                    .axes
                    .each_ref()
                    .map(|a| a.as_ref().map(|t| (t.origin, t.scale))),
            ),
            None => (false, [None; 3]),
        };
        // Judged from the tracked fit when x's is adequate (y and z cannot reach the limit).
        let fitted = |m: &Monitor, key| {
            let state: &SensorState = &m.sensors[key];
            let Some(track) = state.sway.axes[0].as_ref().filter(|_| state.sway.armed) else {
                return false;
            };
            let front = state
                .sway
                .index(state.window.front().expect("a window").t_ns);
            let summary = state.bounds.summaries()[0];
            let geometry = Geometry {
                rate_hz: 100.0,
                scale: track.scale,
                grid_start: (front - track.origin) as f64,
                grid_len: 1000,
                largest: summary.largest_accel,
                highpass: state.highpass.as_ref().map(HighPass::response),
            };
            sinefit::fit_at(&track.moments, track.omega, &geometry, summary.mean_u)
                .is_some_and(|a| a.fit.is_some())
        };
        let (mut spent, mut judged) = (std::time::Duration::ZERO, 0u64);
        let (mut tracked, mut retuned, mut moved, mut searched) = (0u64, 0u64, 0u64, 0u64);
        let batches_a_second = 100 / batch_samples;
        for seq in 0..seconds * batches_a_second {
            for (name, key) in names.iter().zip(&keys) {
                let samples = (0..batch_samples)
                    .map(|i| {
                        let t = (seq * batch_samples + i) as f64 / 100.0;
                        let x = 1.9 * (std::f64::consts::TAU * 1.3 * t).sin();
                        let mut e = || noise.sample(&mut rng) as f32;
                        CorrectedSample {
                            accel_mps2: [x as f32 + e(), e(), 9.81 + e()],
                            uncertainty_mps2: [0.01; 3],
                            flags: 0,
                        }
                    })
                    .collect();
                let b = corrected(name, seq, samples);
                let now = t0 + time::Duration::milliseconds((seq * batch_samples * 10) as i64);
                let before = tracks(&m, key);
                let start = std::time::Instant::now();
                m.on_corrected(&hq, &b, now);
                let took = start.elapsed();
                if seq < warm_up * batches_a_second {
                    continue;
                }
                spent += took;
                judged += 1;
                tracked += u64::from(fitted(&m, key));
                let after = tracks(&m, key);
                if !after.0 {
                    continue;
                }
                if !before.0 {
                    searched += 1;
                    continue;
                }
                // Every build starts the sums at the window's first sample: one whose origin
                // was more than a window behind was rebuilt for that.
                let rebuilt = before.1.iter().zip(&after.1).filter(|(b, a)| b != a);
                if rebuilt
                    .clone()
                    .any(|(b, a)| b.zip(*a).is_some_and(|(b, a)| (a.0 - b.0) as f64 <= b.1))
                {
                    retuned += 1;
                } else if rebuilt.count() > 0 {
                    moved += 1;
                }
            }
        }
        let per_batch = |n: u64| n as f64 / judged as f64;
        println!(
            "{judged} batches of {batch_samples} judged: {:.3} µs a sample ({:.2} M samples/s on \
             one core); from the tracked fit {:.4}, retuned {:.4}, origin moved {:.4}, armed \
             {:.4} a batch",
            spent.as_secs_f64() / (judged * batch_samples) as f64 * 1e6,
            (judged * batch_samples) as f64 / spent.as_secs_f64() / 1e6,
            per_batch(tracked),
            per_batch(retuned),
            per_batch(moved),
            per_batch(searched),
        );
    }
}
