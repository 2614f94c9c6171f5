//! Three co-located sensors: each one's own noise and their gains relative to each other, with
//! no reference sensor (Sleeman, Van Wettum & Trampert, BSSA 96(1), 2006).
//!
//! Three sensors `A`, `B`, `C` on the same part of a structure read the same motion `U` through
//! their own responses, each with noise of its own: `Xᵢ = Hᵢ·U + nᵢ`. With the cross-spectra
//! `Pᵢⱼ = Σ conj(Xᵢ)·Xⱼ` over a band's bins and the segments of an estimate (B's and C's readings
//! turned into A's frame by their mountings; the same Hann-windowed DFT on a common time grid
//! as [`crate::colocated`]), the noise of each cancels from every product of two others:
//!
//! ```text
//! Nᵢ = Pᵢᵢ − Pⱼᵢ·Pᵢₖ / Pⱼₖ               (i's own noise, j and k the other two)
//! H_B / H_A = P_CB / P_CA,   H_C / H_A = P_BC / P_BA
//! ```
//!
//! `Nᵢ` over the Hann window's `Σw²` and the bins is the per-sample white-noise variance of
//! sensor `i`'s corrected reading along the axis, which the report gives as a ratio to what its
//! record states; the gain ratios need no record's noise at all (the pair's H₁ does).
//! Uncertainty: a delete-one jackknife over twenty sub-spans of the estimate (ν = 19), each
//! replicate the same formulas on the rest; the gain ratios' comparison with 1 adds the two
//! records' gain uncertainties along the axis, as the pair test does. Estimates are published
//! per axis and hour; the verdicts are `watch` beyond the 99 % interval, never `suspect` (the
//! pair tests hold the budget for that).

use nalgebra::Complex;
use triax_calibration::corrector::Corrector;
use triax_calibration::student::{t_quantile, welch_satterthwaite, MAX_DOF};
use triax_protocol::record::{CalibrationRecord, SetKind};

use crate::colocated::{feed_segments, gain_variance, Segment, Spectrum};
use crate::config::HealthError;
use crate::cusum::Verdict;
use crate::report::{TestReport, Unjudged};

/// One solution: each member's noise variance and B's and C's gains over A's.
type Solution = ([f64; 3], [f64; 2]);

/// Sub-spans of an estimate for its jackknife.
const JACKKNIFE: usize = 20;
/// Segments one sensor may hold while the others catch up.
const PENDING: usize = 8;

/// A group of three's settings.
#[derive(Debug, Clone, PartialEq)]
pub struct TripleConfig {
    /// Band the spectra are taken in, Hz: where the motion stands well above every sensor's
    /// noise.
    pub band_hz: [f64; 2],
    pub segment_s: f64,
    /// B's and C's axes in A's frame: `a_A = mounting · a_X` for the same motion.
    pub mountings: [[[f64; 3]; 3]; 2],
    /// Span of segments one estimate takes, s.
    pub estimate_s: f64,
    /// Probability of the interval beyond which an estimate is `watch`.
    pub watch_probability: f64,
    /// Estimates whose least coherence between two members is below this are too quiet to
    /// separate motion from noise (left out).
    pub min_coherence: f64,
}

impl Default for TripleConfig {
    fn default() -> Self {
        let identity = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
        TripleConfig {
            band_hz: [1.0, 5.0],
            segment_s: 5.0,
            mountings: [identity, identity],
            estimate_s: 3600.0,
            watch_probability: 0.99,
            min_coherence: 0.5,
        }
    }
}

impl TripleConfig {
    /// Refuses settings that would make the estimate meaningless, by field.
    pub fn validate(&self) -> Result<(), HealthError> {
        let pair = crate::colocated::PairConfig {
            band_hz: self.band_hz,
            segment_s: self.segment_s,
            estimate_s: self.estimate_s,
            ..Default::default()
        };
        pair.validate()?;
        for m in &self.mountings {
            crate::colocated::PairConfig {
                mounting: *m,
                ..pair.clone()
            }
            .validate()?;
        }
        if !(0.0..1.0).contains(&self.min_coherence) {
            return Err(HealthError::Config {
                field: "min_coherence",
                problem: format!("{} is not in 0 to 1", self.min_coherence),
            });
        }
        if !(0.5..1.0).contains(&self.watch_probability) {
            return Err(HealthError::Config {
                field: "watch_probability",
                problem: format!("{} is not in 0.5 to 1", self.watch_probability),
            });
        }
        Ok(())
    }
}

/// One estimate of a triple along one axis of A's frame.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TripleEstimate {
    pub end_ns: i64,
    /// Each sensor's own white-noise standard deviation per sample, m/s², and its standard
    /// uncertainty (ν = `dof`).
    pub noise_mps2: [f64; 3],
    pub noise_uncertainty_mps2: [f64; 3],
    /// What each record states for the same (its output noise through its dynamic set).
    pub stated_noise_mps2: [f64; 3],
    /// B's and C's gains over A's, and their standard uncertainties from the estimate alone.
    pub gain: [f64; 2],
    pub gain_uncertainty: [f64; 2],
    pub dof: f64,
}

#[derive(Debug, Clone)]
struct Member {
    segment: Segment,
    pending: Vec<Spectrum>,
    spare: Vec<Vec<[f64; 2]>>,
    /// Corrected white-noise variance per axis of A's frame, as the record states it.
    stated_var: [f64; 3],
    /// Relative gain variance per axis of A's frame, and the reciprocal of its ν.
    gain_var: [f64; 3],
    gain_inv_dof: f64,
}

/// Cross-spectra of the three per axis: `p[axis][i][j] = Σ conj(Xᵢ)·Xⱼ`, and `Σw²·bins`.
#[derive(Debug, Clone, Copy, PartialEq)]
struct Cross {
    p: [[[Complex<f64>; 3]; 3]; 3],
    weight: f64,
}

impl Default for Cross {
    fn default() -> Self {
        Cross {
            p: [[[Complex::new(0.0, 0.0); 3]; 3]; 3],
            weight: 0.0,
        }
    }
}

impl Cross {
    fn add(&mut self, o: &Cross, sign: f64) {
        for axis in 0..3 {
            for i in 0..3 {
                for j in 0..3 {
                    self.p[axis][i][j] += o.p[axis][i][j] * sign;
                }
            }
        }
        self.weight += sign * o.weight;
    }

    /// The least coherence `|Pᵢⱼ|²/(Pᵢᵢ·Pⱼⱼ)` of two members along `axis`.
    fn coherence(&self, axis: usize) -> f64 {
        let p = &self.p[axis];
        [(0, 1), (1, 2), (0, 2)]
            .map(|(i, j)| p[i][j].norm_sqr() / (p[i][i].re * p[j][j].re).max(f64::MIN_POSITIVE))
            .into_iter()
            .fold(1.0, f64::min)
    }

    /// Each sensor's noise variance per sample and B's and C's gains over A's, along `axis`.
    fn solve(&self, axis: usize) -> Option<Solution> {
        let p = &self.p[axis];
        if self.weight <= 0.0 {
            return None;
        }
        let mut noise = [0.0; 3];
        for (i, n) in noise.iter_mut().enumerate() {
            let (j, k) = ((i + 1) % 3, (i + 2) % 3);
            if p[j][k].norm_sqr() == 0.0 {
                return None;
            }
            let coherent = p[j][i] * p[i][k] / p[j][k];
            *n = (p[i][i].re - coherent.re) / self.weight;
        }
        if p[2][0].norm_sqr() == 0.0 || p[1][0].norm_sqr() == 0.0 {
            return None;
        }
        let gain = [(p[2][1] / p[2][0]).re, (p[1][2] / p[1][0]).re];
        Some((noise, gain))
    }
}

#[derive(Debug, Clone, Copy, Default)]
struct AxisState {
    latest: Option<TripleEstimate>,
    estimates: u64,
}

/// The three-channel check of a group of three co-located sensors, each under one record.
#[derive(Debug, Clone)]
pub struct ColocatedTriple {
    config: TripleConfig,
    members: [Member; 3],
    sums: Cross,
    parts: Vec<Cross>,
    segments: u32,
    segments_per_estimate: u32,
    axes: [AxisState; 3],
    completed: Vec<Spectrum>,
}

impl ColocatedTriple {
    /// A check of `records[0]` (A), `records[1]` (B) and `records[2]` (C).
    pub fn new(
        records: [&CalibrationRecord; 3],
        config: &TripleConfig,
    ) -> Result<ColocatedTriple, HealthError> {
        config.validate()?;
        let identity = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
        let turns = [identity, config.mountings[0], config.mountings[1]];
        let mut members = Vec::with_capacity(3);
        for (record, turn) in records.iter().zip(&turns) {
            let corrector = Corrector::from_record(record)?;
            let set = corrector.set(SetKind::Dynamic);
            let noise = set.covariance_filtered_parts([0.0; 3], 1.0, [0.0; 3]).noise;
            let mut stated_var = [0.0; 3];
            for (i, v) in stated_var.iter_mut().enumerate() {
                for j in 0..3 {
                    for k in 0..3 {
                        *v += turn[i][j] * noise[j][k] * turn[i][k];
                    }
                }
            }
            let (gain_var, gain_inv_dof) = gain_variance(record, set, turn);
            let segment = Segment::for_band(config.band_hz, config.segment_s);
            let bins = segment.bins();
            members.push(Member {
                segment,
                pending: Vec::with_capacity(PENDING + 1),
                spare: (0..PENDING + 1).map(|_| vec![[0.0; 2]; 3 * bins]).collect(),
                stated_var,
                gain_var,
                gain_inv_dof,
            });
        }
        let members: [Member; 3] = members.try_into().map_err(|_| HealthError::Config {
            field: "records",
            problem: "a triple is three sensors".into(),
        })?;
        Ok(ColocatedTriple {
            members,
            sums: Cross::default(),
            parts: vec![Cross::default(); JACKKNIFE],
            segments: 0,
            segments_per_estimate: (config.estimate_s / config.segment_s).round() as u32,
            axes: [AxisState::default(); 3],
            completed: Vec::with_capacity(2),
            config: config.clone(),
        })
    }

    /// Member `member`'s (0 A, 1 B, 2 C) corrected readings, m/s² in its own frame, the first
    /// at `timestamp_ns`.
    pub fn feed(
        &mut self,
        member: usize,
        timestamp_ns: i64,
        sample_rate_hz: f64,
        accel_mps2: &[[f64; 3]],
    ) {
        let Some(m) = self.members.get_mut(member) else {
            return;
        };
        let turn = (member > 0).then(|| self.config.mountings[member - 1]);
        let mut completed = std::mem::take(&mut self.completed);
        feed_segments(
            &mut m.segment,
            &mut m.spare,
            self.config.segment_s,
            turn.as_ref(),
            timestamp_ns,
            sample_rate_hz,
            accel_mps2,
            |s| completed.push(s),
        );
        for s in completed.drain(..) {
            self.complete(member, s);
        }
        self.completed = completed;
    }

    fn complete(&mut self, member: usize, spectrum: Spectrum) {
        let index = spectrum.index;
        let m = &mut self.members[member];
        // A restart's earlier numbering, or a segment its peers will never deliver (a gap).
        while let Some(i) = m.pending.iter().position(|s| s.index >= index) {
            let stale = m.pending.swap_remove(i);
            m.spare.push(stale.x);
        }
        if m.pending.len() == PENDING {
            if let Some(oldest) = (0..m.pending.len()).min_by_key(|&i| m.pending[i].index) {
                let stale = m.pending.swap_remove(oldest);
                m.spare.push(stale.x);
            }
        }
        m.pending.push(spectrum);
        let found: Vec<Option<usize>> = self
            .members
            .iter()
            .map(|m| m.pending.iter().position(|s| s.index == index))
            .collect();
        if found.iter().all(Option::is_some) {
            let taken: Vec<Spectrum> = self
                .members
                .iter_mut()
                .zip(&found)
                .map(|(m, at)| m.pending.swap_remove(at.unwrap_or(0)))
                .collect();
            self.combine(&taken, index);
            for (m, s) in self.members.iter_mut().zip(taken) {
                m.spare.push(s.x);
                // Older segments can no longer find their peers.
                while let Some(i) = m.pending.iter().position(|p| p.index < index) {
                    let stale = m.pending.swap_remove(i);
                    m.spare.push(stale.x);
                }
            }
        }
    }

    fn combine(&mut self, x: &[Spectrum], index: i64) {
        let bins = self.members[0].segment.bins();
        let part = (self.segments as usize * JACKKNIFE / self.segments_per_estimate as usize)
            .min(JACKKNIFE - 1);
        let mut c = Cross {
            weight: x[0].sum_w2 * bins as f64,
            ..Cross::default()
        };
        for axis in 0..3 {
            for k in 0..bins {
                let v = [0, 1, 2].map(|m| {
                    let z = x[m].x[axis * bins + k];
                    Complex::new(z[0], z[1])
                });
                for i in 0..3 {
                    for j in 0..3 {
                        c.p[axis][i][j] += v[i].conj() * v[j];
                    }
                }
            }
        }
        self.sums.add(&c, 1.0);
        self.parts[part].add(&c, 1.0);
        self.segments += 1;
        if self.segments >= self.segments_per_estimate {
            let end_ns = (index + 1) * (self.config.segment_s * 1e9).round() as i64;
            self.estimate(end_ns);
        }
    }

    fn estimate(&mut self, end_ns: i64) {
        for axis in 0..3 {
            if self.sums.coherence(axis) < self.config.min_coherence {
                continue;
            }
            let Some((noise, gain)) = self.sums.solve(axis) else {
                continue;
            };
            let mut replicates: Vec<Solution> = Vec::with_capacity(JACKKNIFE);
            for part in &self.parts {
                if part.weight == 0.0 {
                    continue;
                }
                let mut rest = self.sums;
                rest.add(part, -1.0);
                if let Some(r) = rest.solve(axis) {
                    replicates.push(r);
                }
            }
            let m = replicates.len();
            if m < 2 {
                continue;
            }
            let spread = |f: &dyn Fn(&Solution) -> f64| {
                let mean = replicates.iter().map(f).sum::<f64>() / m as f64;
                let ss: f64 = replicates.iter().map(|r| (f(r) - mean).powi(2)).sum();
                ((m as f64 - 1.0) / m as f64 * ss).sqrt()
            };
            // σ = √N; u(σ) = u(N)/(2σ).
            let noise_mps2 = noise.map(|n| n.max(0.0).sqrt());
            let noise_uncertainty_mps2 = [0, 1, 2]
                .map(|i| spread(&|r: &Solution| r.0[i]) / (2.0 * noise_mps2[i].max(1e-300)));
            let gain_uncertainty = [0, 1].map(|i| spread(&|r: &Solution| r.1[i]));
            let estimate = TripleEstimate {
                end_ns,
                noise_mps2,
                noise_uncertainty_mps2,
                stated_noise_mps2: [0, 1, 2].map(|i| self.members[i].stated_var[axis].sqrt()),
                gain,
                gain_uncertainty,
                dof: (m - 1) as f64,
            };
            let a = &mut self.axes[axis];
            a.latest = Some(estimate);
            a.estimates += 1;
        }
        self.sums = Cross::default();
        for part in &mut self.parts {
            *part = Cross::default();
        }
        self.segments = 0;
    }

    /// The latest estimate per axis of A's frame.
    pub fn latest(&self) -> [Option<TripleEstimate>; 3] {
        [0, 1, 2].map(|i| self.axes[i].latest)
    }

    /// Member `member`'s own noise per axis of A's frame, as a ratio of its standard deviation
    /// to what its record states: `watch` beyond the 99 % interval.
    pub fn noise_report(&self, member: usize) -> [TestReport; 3] {
        [0, 1, 2].map(|axis| {
            let a = &self.axes[axis];
            let Some(e) = a.latest else {
                return TestReport::unjudged(Unjudged::NoEstimate);
            };
            let stated = e.stated_noise_mps2[member];
            if stated <= 0.0 {
                return TestReport::unjudged(Unjudged::NoStatedNoise);
            }
            let ratio = e.noise_mps2[member] / stated;
            let u = e.noise_uncertainty_mps2[member] / stated;
            let k = t_quantile(e.dof.max(1.0) as u32, self.config.watch_probability);
            let verdict = if (ratio - 1.0).abs() > k * u {
                Verdict::Watch
            } else {
                Verdict::Ok
            };
            TestReport {
                verdict,
                judged: true,
                statistic: ratio,
                uncertainty: u,
                since_ns: (verdict == Verdict::Watch).then_some(e.end_ns),
                observations: a.estimates,
                reason: None,
                ..TestReport::pending()
            }
        })
    }

    /// Member `member`'s gain (B: 1, C: 2) over A's per axis minus 1, against the two records'
    /// gain uncertainties; A's own (member 0) is not judged (it is the reference).
    pub fn gain_report(&self, member: usize) -> [TestReport; 3] {
        [0, 1, 2].map(|axis| {
            let a = &self.axes[axis];
            let (Some(e), 1..=2) = (a.latest, member) else {
                return TestReport::unjudged(Unjudged::NoEstimate);
            };
            let g = member - 1;
            let (ua, ub) = (
                self.members[0].gain_var[axis],
                self.members[member].gain_var[axis],
            );
            let parts = [
                (e.gain_uncertainty[g].powi(2), 1.0 / e.dof),
                (ua, self.members[0].gain_inv_dof),
                (ub, self.members[member].gain_inv_dof),
            ];
            let var: f64 = parts.iter().map(|(v, _)| v).sum();
            let nu = welch_satterthwaite(&parts).clamp(1.0, f64::from(MAX_DOF));
            let k = t_quantile(nu as u32, self.config.watch_probability);
            let d = e.gain[g] - 1.0;
            let verdict = if d.abs() > k * var.sqrt() {
                Verdict::Watch
            } else {
                Verdict::Ok
            };
            TestReport {
                verdict,
                judged: true,
                statistic: d,
                uncertainty: var.sqrt(),
                since_ns: (verdict == Verdict::Watch).then_some(e.end_ns),
                observations: a.estimates,
                reason: None,
                ..TestReport::pending()
            }
        })
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::rngs::SmallRng;
    use rand::{Rng, SeedableRng};
    use rand_distr::StandardNormal;
    use triax_protocol::record::sample;

    fn unit_record(id: &str) -> CalibrationRecord {
        let mut r = sample::record(id, 1);
        for set in [&mut r.static_set, &mut r.dynamic] {
            set.sensitivity = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]];
            set.offset = [0.0; 3];
        }
        r.sensor.output_noise = Some([0.01; 3]);
        r
    }

    /// A motion common to the three (two tones and white noise in the band) with each
    /// sensor's own white noise at 0.01, 0.02 and 0.005 m/s², B reading 1 % high on x and C
    /// 2 % low: the noises and gains come back within their stated uncertainties, and the
    /// noises do not depend on the motion's level.
    #[test]
    fn three_sensors_give_their_own_noises_and_gains() {
        let config = TripleConfig {
            estimate_s: 600.0,
            ..TripleConfig::default()
        };
        let records = [unit_record("a"), unit_record("b"), unit_record("c")];
        let mut t = ColocatedTriple::new([&records[0], &records[1], &records[2]], &config).unwrap();
        let mut rng = SmallRng::seed_from_u64(4);
        let fs = 100.0;
        let sigma = [0.01, 0.02, 0.005];
        let gain = [1.0, 1.01, 0.98];
        let mut bufs = vec![Vec::new(); 3];
        for batch in 0..6_100 {
            bufs.iter_mut().for_each(Vec::clear);
            for i in 0..10 {
                let n = batch * 10 + i;
                let time = n as f64 / fs;
                let u = 0.02 * (2.0 * std::f64::consts::PI * 1.3 * time).sin()
                    + 0.01 * (2.0 * std::f64::consts::PI * 3.7 * time + 0.4).sin()
                    + 0.02 * rng.sample::<f64, _>(StandardNormal);
                for (m, b) in bufs.iter_mut().enumerate() {
                    let e = |rng: &mut SmallRng| sigma[m] * rng.sample::<f64, _>(StandardNormal);
                    b.push([gain[m] * u + e(&mut rng), e(&mut rng), e(&mut rng)]);
                }
            }
            let t0 = 1_767_225_600_000_000_000i64 + batch as i64 * 100_000_000;
            for (m, b) in bufs.iter().enumerate() {
                t.feed(m, t0, fs, b);
            }
        }
        let e = t.latest()[0].expect("an estimate on x");
        for (m, s) in sigma.iter().enumerate() {
            let z = (e.noise_mps2[m] - s) / e.noise_uncertainty_mps2[m];
            assert!(z.abs() < 4.0, "member {m}: {e:?}");
            assert!(e.noise_uncertainty_mps2[m] < 0.1 * s, "{e:?}");
        }
        for g in 0..2 {
            let z = (e.gain[g] - gain[g + 1]) / e.gain_uncertainty[g];
            assert!(z.abs() < 4.0, "gain {g}: {e:?}");
        }
        // y and z carry noise alone: no coherent motion, no estimate.
        assert!(t.latest()[1].is_none() && t.latest()[2].is_none());
        assert_eq!(t.gain_report(0)[0].reason, Some(Unjudged::NoEstimate));
        let r = t.noise_report(1)[0];
        assert!(
            r.judged && (r.statistic - 2.0).abs() < 4.0 * r.uncertainty,
            "{r:?}"
        );
        assert_eq!(r.verdict, Verdict::Watch, "B's noise is twice its record's");
    }
}
