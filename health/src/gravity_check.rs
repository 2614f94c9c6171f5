//! The gravity check: a quiet sensor reads local gravity, whatever its orientation.
//!
//! **Observations.** Consecutive quiet blocks ([`crate::monitor`] decides) make a stretch of
//! `stretch_s`. Each block's mean output is corrected through the record's *static* set at the
//! block's temperature (`SetCorrector::at_temperature`: the same correction the gateway
//! applies); the correction is linear at a fixed temperature, so the block's mean corrected
//! reading is the correction of its mean output. A stretch gives the mean `ā` of its blocks,
//! its magnitude `m = |ā|` and direction `n̂ = ā/m`, and the noise of `m`: to first order
//! `δm = n̂·δā`, so `u²_noise = n̂ᵀ·C·n̂ / n` with `C` the covariance of the n block means. Block
//! means rather than samples, because vibration is correlated from sample to sample and only
//! its effect on the means is wanted; the larger of this stretch's estimate and one pooled over
//! the last stretches (an exponential average, ν up to ≈ 50 stretches' worth) is taken.
//!
//! **Absolute test** (is the record consistent with gravity now?). `D = m̄ − g`, `m̄` the
//! noise-weighted mean magnitude of every stretch so far, against
//!
//! ```text
//! u²(D) = n̂ᵀ·J·Σ_θ·Jᵀ·n̂ + n̂ᵀ·diag(u²_stated)·n̂ + σ²_β·ΔT̄² + 1/Σw + u²(g) + s²
//! ```
//!
//! the record's 12×12 parameter covariance through `a = S⁻¹·V + q` (`J = ∂a/∂θ` at the mean
//! output, as the corrector propagates it) along the measured direction, its stated part, the
//! temperature model's (`σ²_β` per °C², below) at the stretches' mean distance from the
//! model's reference, the mean's noise, local gravity's, and the stated stability `s`. Its
//! degrees of freedom are Welch–Satterthwaite's over the parts (the record's ν for the
//! covariances, the pooled noise's, infinitely many for g and s). The record's error does not
//! average away, so the test is not a CUSUM: it looks at the mean at `absolute_min_stretches`
//! stretches and at every doubling of their count after, and spends its false-alarm
//! probability over the looks, half of what is left at each (`α_j = α·2^{−j}`, which sum to
//! α): `suspect` beyond Student's t at `1 − α_j`, α the sensor's share of `1 −
//! absolute_suspect_probability` (split among its absolute tests), and `watch` likewise for
//! `absolute_watch_probability`. A healthy sensor with an honest record is then `suspect` with
//! probability at most α over the record's life, however long it is watched.
//!
//! **Temperature.** With `ΔT = T − T₀`, the model's coefficients' errors move `a` by
//! `ΔT·(δc_q − S⁻¹·diag(V₀)·δc_g)`, so `m` by `ΔT·β` with `β = gᵀ·δc`,
//! `g = (n̂, −(n̂ᵀS⁻¹)_j·V₀_j)`; `σ²_β = gᵀ·Σ_T·g` from the record's 6×6 covariance.
//!
//! **Relative test** (has the sensor changed since the record came into force?). After
//! `baseline_stretches` stretches spanning `baseline_s`, the baseline is the weighted
//! least-squares line `m = m₀ + b·ΔT` with the prior `b ~ N(0, σ²_β)`: where the temperature
//! model's error along `n̂` shows in the data, the baseline learns it; where the day's range is
//! too small to show it, the prior keeps `b` near what the record claims, with its
//! uncertainty. The calibration's own error is common to the baseline and every later
//! stretch, and cancels. Each later stretch gives `d = m − m₀ − b·ΔT` with
//! `u² = u²_noise + s² + [1 ΔT]·A⁻¹·[1 ΔT]ᵀ` (the line's covariance), and a two-sided CUSUM of
//! `δ(z − δ/2)`, `z = d/u`, `δ = relative_shift_mps2/u`: the exact log-likelihood ratio of a
//! shift of the design size, with the run-length bounds of [`crate::cusum`].

use triax_calibration::corrector::{SetCorrector, TemperatureCheck};

use triax_calibration::student::{t_quantile, welch_satterthwaite, MAX_DOF};
use triax_protocol::record::{CalibrationRecord, SetKind};

use crate::config::HealthConfig;
use crate::cusum::{Sequential, Thresholds, Verdict};
use crate::gravity::LocalGravity;
use crate::report::{TestReport, Unjudged};

/// Weight of the newest stretch in the pooled noise.
const POOL_LAMBDA: f64 = 0.02;

/// What the gravity check needs of the record's static set.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct StaticModel {
    set: SetCorrector,
    s_inv: [[f64; 3]; 3],
    thermal: Option<ThermalPrior>,
    inv_dof_parameters: f64,
    inv_dof_stated: f64,
}

#[derive(Debug, Clone, PartialEq)]
struct ThermalPrior {
    reference_c: f64,
    gain_per_c: [f64; 3],
    covariance: [[f64; 6]; 6],
    inv_dof: f64,
}

impl StaticModel {
    pub fn new(record: &CalibrationRecord, set: &SetCorrector) -> StaticModel {
        let cal = record.set(SetKind::Static);
        let columns = [[1.0, 0.0, 0.0], [0.0, 1.0, 0.0], [0.0, 0.0, 1.0]].map(|e| set.scale(e));
        let s_inv = [0, 1, 2].map(|k| [0, 1, 2].map(|j| columns[j][k]));
        StaticModel {
            set: set.clone(),
            s_inv,
            thermal: record.temperature.as_ref().map(|t| ThermalPrior {
                reference_c: t.reference_c,
                gain_per_c: t.gain_per_c.unwrap_or([0.0; 3]),
                covariance: t.covariance,
                inv_dof: t.covariance_dof.map_or(0.0, |nu| 1.0 / nu),
            }),
            inv_dof_parameters: cal.covariance_dof.map_or(0.0, |nu| 1.0 / nu),
            inv_dof_stated: cal.uncertainty_dof.map_or(0.0, |nu| 1.0 / nu),
        }
    }

    /// S⁻¹ of the static set, m/s² per output unit.
    pub fn s_inv(&self) -> &[[f64; 3]; 3] {
        &self.s_inv
    }

    /// The corrected mean of a block with mean output `mean_output`; none when the record
    /// models temperature and the block's is missing or outside the calibrated range (the
    /// gateway flags those `outside_temperature`: not a clean reading).
    pub fn block_accel(
        &self,
        mean_output: [f64; 3],
        temperature_c: Option<f64>,
    ) -> Option<[f64; 3]> {
        match self.set.temperature_check(temperature_c) {
            TemperatureCheck::NotModelled => Some(self.set.accel(mean_output)),
            TemperatureCheck::Inside => {
                let at = self.set.at_temperature(temperature_c?)?;
                Some(at.accel(mean_output))
            }
            TemperatureCheck::Outside | TemperatureCheck::Missing => None,
        }
    }

    /// ΔT from the model's reference, 0 without a model.
    fn delta_t(&self, temperature_c: Option<f64>) -> f64 {
        match (&self.thermal, temperature_c) {
            (Some(t), Some(c)) => c - t.reference_c,
            _ => 0.0,
        }
    }

    /// Variance per °C² of the magnitude along `n` from the temperature model's coefficients,
    /// at mean output `v` and temperature difference `delta_t`.
    pub fn thermal_slope_var(&self, n: [f64; 3], v: [f64; 3], delta_t: f64) -> f64 {
        let Some(t) = &self.thermal else {
            return 0.0;
        };
        let nt_s_inv = [0, 1, 2].map(|j| (0..3).map(|k| n[k] * self.s_inv[k][j]).sum::<f64>());
        let v0 = [0, 1, 2].map(|j| v[j] / (1.0 + t.gain_per_c[j] * delta_t));
        let g = [
            n[0],
            n[1],
            n[2],
            -nt_s_inv[0] * v0[0],
            -nt_s_inv[1] * v0[1],
            -nt_s_inv[2] * v0[2],
        ];
        let mut var = 0.0;
        for (i, gi) in g.iter().enumerate() {
            for (j, gj) in g.iter().enumerate() {
                var += gi * t.covariance[i][j] * gj;
            }
        }
        var.max(0.0)
    }

    /// Parameter and stated variances of the magnitude along `n` at mean output `v`, from the
    /// corrector's propagation of the record's covariance.
    pub fn calibration_var(&self, n: [f64; 3], v: [f64; 3]) -> (f64, f64) {
        let parts = self.set.covariance_filtered_parts(v, 0.0, [0.0; 3]);
        let along = |m: &[[f64; 3]; 3]| {
            let mut s = 0.0;
            for k in 0..3 {
                for l in 0..3 {
                    s += n[k] * m[k][l] * n[l];
                }
            }
            s.max(0.0)
        };
        (along(&parts.parameters), along(&parts.stated))
    }
}

/// One quiet stretch, reduced.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GravityObservation {
    /// Time of the stretch's last sample, ns.
    pub end_ns: i64,
    pub magnitude_mps2: f64,
    pub direction: [f64; 3],
    /// Variance of the magnitude from noise and vibration, (m/s²)², and its degrees of freedom.
    pub noise_var: f64,
    pub noise_dof: f64,
    pub temperature_c: Option<f64>,
    pub mean_output: [f64; 3],
}

#[derive(Debug, Clone, Default, PartialEq)]
struct Stretch {
    blocks: u32,
    shift: [f64; 3],
    sum: [f64; 3],
    sum_sq: [[f64; 3]; 3],
    sum_output: [f64; 3],
    sum_temperature: f64,
    has_temperature: bool,
}

/// A test that looks at an accumulating estimate at counts `first·2^{j−1}`, spending `α·2^{−j}`
/// of its false-alarm probability at look `j` (which sum to α whatever the number of looks).
#[derive(Debug, Clone, Copy, PartialEq)]
pub(crate) struct Looks {
    first: u64,
    watch_alpha: f64,
    suspect_alpha: f64,
    /// Looks taken, and the verdict of the last one.
    taken: u32,
    watch: bool,
    suspect: bool,
}

impl Looks {
    pub fn new(first: u64, watch_alpha: f64, suspect_alpha: f64) -> Looks {
        Looks {
            first: first.max(1),
            watch_alpha,
            suspect_alpha,
            taken: 0,
            watch: false,
            suspect: false,
        }
    }

    /// Whether `count` observations are a look: the first, then every doubling.
    pub fn due(&self, count: u64) -> bool {
        count == self.first << self.taken.min(62)
    }

    /// Takes the look at standardised distance `z = |d|/u` with `nu` degrees of freedom;
    /// returns whether it found `suspect` (which then latches).
    pub fn take(&mut self, z: f64, nu: f64) -> bool {
        self.taken += 1;
        let j = self.taken.min(60) as i32;
        let nu = nu.floor().clamp(1.0, f64::from(MAX_DOF)) as u32;
        let factor = |alpha: f64| t_quantile(nu, 1.0 - (alpha * 0.5f64.powi(j)).max(1e-15));
        self.watch = z > factor(self.watch_alpha);
        if !self.suspect && z > factor(self.suspect_alpha) {
            self.suspect = true;
            return true;
        }
        false
    }

    pub fn taken(&self) -> u32 {
        self.taken
    }

    pub fn watch(&self) -> bool {
        self.watch
    }
}

#[derive(Debug, Clone, PartialEq)]
struct Absolute {
    gravity: LocalGravity,
    looks: Looks,
    sum_w: f64,
    sum_wd: f64,
    sum_wdt: f64,
    count: u64,
    first_ns: Option<i64>,
    /// The latest stretch's calibration variances along its direction.
    param_var: f64,
    stated_var: f64,
    thermal_slope_var: f64,
    noise_dof: f64,
    suspect_since_ns: Option<i64>,
    latest: Option<(f64, f64, f64)>,
}

#[derive(Debug, Clone, Copy, PartialEq)]
struct Baseline {
    /// m = reference + θ₀ + θ₁·ΔT, with covariance `cov` of θ.
    reference_mps2: f64,
    theta: [f64; 2],
    cov: [[f64; 2]; 2],
}

#[derive(Debug, Clone, PartialEq)]
struct Relative {
    shift_mps2: f64,
    stretches: u32,
    span_s: f64,
    n: u32,
    first_ns: Option<i64>,
    reference_mps2: f64,
    sums: [f64; 5],
    slope_prior_var: Option<f64>,
    baseline: Option<Baseline>,
    seq: Sequential,
    /// Σw and Σw·d over the current excursion of the up and down CUSUMs.
    up: (f64, f64),
    down: (f64, f64),
    latest: Option<(f64, f64)>,
    prediction_var: f64,
}

/// The gravity check of one sensor under one record.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct GravityCheck {
    model: StaticModel,
    stretch_blocks: u32,
    stability_var: f64,
    stretch: Stretch,
    pooled_var: f64,
    pooled_dof: f64,
    stretches: u64,
    absolute: Option<Absolute>,
    relative: Relative,
}

impl GravityCheck {
    /// `sequential` is how many sequential tests share the sensor's false-alarm budget.
    pub fn new(model: StaticModel, config: &HealthConfig, sequential: u32) -> GravityCheck {
        let per_day = 86_400.0 / config.stretch_s;
        let tests = f64::from(sequential.max(1));
        // The absolute tests of the sensor: this one and three a co-located pair.
        let absolute = f64::from(1 + 3 * config.colocated_pairs);
        GravityCheck {
            model,
            stretch_blocks: (config.stretch_s / config.block_s).round().max(2.0) as u32,
            stability_var: config.stability_mps2.powi(2),
            stretch: Stretch::default(),
            pooled_var: 0.0,
            pooled_dof: 0.0,
            stretches: 0,
            absolute: config.local_gravity.map(|gravity| Absolute {
                gravity,
                looks: Looks::new(
                    u64::from(config.absolute_min_stretches),
                    (1.0 - config.absolute_watch_probability) / absolute,
                    (1.0 - config.absolute_suspect_probability) / absolute,
                ),
                sum_w: 0.0,
                sum_wd: 0.0,
                sum_wdt: 0.0,
                count: 0,
                first_ns: None,
                param_var: 0.0,
                stated_var: 0.0,
                thermal_slope_var: 0.0,
                noise_dof: 0.0,
                suspect_since_ns: None,
                latest: None,
            }),
            relative: Relative {
                shift_mps2: config.relative_shift_mps2,
                stretches: config.baseline_stretches,
                span_s: config.baseline_s,
                n: 0,
                first_ns: None,
                reference_mps2: 0.0,
                sums: [0.0; 5],
                slope_prior_var: None,
                baseline: None,
                seq: Sequential::new(Thresholds::from_arl(
                    config.watch_arl_days * tests * per_day,
                    config.suspect_arl_days * tests * per_day,
                    2,
                )),
                up: (0.0, 0.0),
                down: (0.0, 0.0),
                latest: None,
                prediction_var: 0.0,
            },
        }
    }

    pub fn model(&self) -> &StaticModel {
        &self.model
    }

    /// Ends the current stretch unfinished: a loud or unusable block, or a break in the stream.
    pub fn interrupt(&mut self) {
        self.stretch = Stretch::default();
    }

    /// A quiet block. Returns the observation when it completes a stretch.
    pub fn quiet_block(
        &mut self,
        end_ns: i64,
        mean_output: [f64; 3],
        temperature_c: Option<f64>,
    ) -> Option<GravityObservation> {
        let Some(a) = self.model.block_accel(mean_output, temperature_c) else {
            self.interrupt();
            return None;
        };
        let s = &mut self.stretch;
        if s.blocks == 0 {
            s.shift = a;
            s.has_temperature = true;
        }
        s.blocks += 1;
        let d = [0, 1, 2].map(|k| a[k] - s.shift[k]);
        for k in 0..3 {
            s.sum[k] += d[k];
            s.sum_output[k] += mean_output[k];
            for l in 0..3 {
                s.sum_sq[k][l] += d[k] * d[l];
            }
        }
        match temperature_c {
            Some(t) => s.sum_temperature += t,
            None => s.has_temperature = false,
        }
        if s.blocks < self.stretch_blocks {
            return None;
        }
        let observation = self.reduce(end_ns);
        self.interrupt();
        self.observe(&observation);
        Some(observation)
    }

    fn reduce(&mut self, end_ns: i64) -> GravityObservation {
        let s = &self.stretch;
        let n = f64::from(s.blocks);
        let mean_d = s.sum.map(|x| x / n);
        let a = [0, 1, 2].map(|k| s.shift[k] + mean_d[k]);
        let magnitude_mps2 = (a[0] * a[0] + a[1] * a[1] + a[2] * a[2]).sqrt();
        let direction = a.map(|x| x / magnitude_mps2);
        let mut block_var = 0.0;
        for k in 0..3 {
            for l in 0..3 {
                let c = (s.sum_sq[k][l] - n * mean_d[k] * mean_d[l]) / (n - 1.0);
                block_var += direction[k] * c * direction[l];
            }
        }
        let block_var = block_var.max(0.0);
        let dof = n - 1.0;
        if self.pooled_dof == 0.0 {
            self.pooled_var = block_var;
            self.pooled_dof = dof;
        } else {
            self.pooled_var += POOL_LAMBDA * (block_var - self.pooled_var);
            self.pooled_dof = (self.pooled_dof + dof).min(dof * (2.0 - POOL_LAMBDA) / POOL_LAMBDA);
        }
        let (var, noise_dof) = if block_var > self.pooled_var {
            (block_var, dof)
        } else {
            (self.pooled_var, self.pooled_dof)
        };
        GravityObservation {
            end_ns,
            magnitude_mps2,
            direction,
            noise_var: var / n,
            noise_dof,
            temperature_c: s.has_temperature.then(|| s.sum_temperature / n),
            mean_output: s.sum_output.map(|x| x / n),
        }
    }

    fn observe(&mut self, o: &GravityObservation) {
        self.stretches += 1;
        let delta_t = self.model.delta_t(o.temperature_c);
        let slope_var = self
            .model
            .thermal_slope_var(o.direction, o.mean_output, delta_t);
        if let Some(abs) = &mut self.absolute {
            let (param_var, stated_var) = self.model.calibration_var(o.direction, o.mean_output);
            abs.param_var = param_var;
            abs.stated_var = stated_var;
            abs.thermal_slope_var = slope_var;
            abs.noise_dof = o.noise_dof;
            let w = 1.0 / o.noise_var.max(f64::MIN_POSITIVE);
            abs.sum_w += w;
            abs.sum_wd += w * (o.magnitude_mps2 - abs.gravity.value_mps2);
            abs.sum_wdt += w * delta_t;
            abs.count += 1;
            abs.first_ns.get_or_insert(o.end_ns);
            let thermal_inv_dof = self.model.thermal.as_ref().map_or(0.0, |t| t.inv_dof);
            let d = abs.sum_wd / abs.sum_w;
            let mean_dt = abs.sum_wdt / abs.sum_w;
            let parts = [
                (abs.param_var, self.model.inv_dof_parameters),
                (abs.stated_var, self.model.inv_dof_stated),
                (abs.thermal_slope_var * mean_dt * mean_dt, thermal_inv_dof),
                (1.0 / abs.sum_w, 1.0 / abs.noise_dof.max(1.0)),
                (abs.gravity.uncertainty_mps2.powi(2), 0.0),
                (self.stability_var, 0.0),
            ];
            let var: f64 = parts.iter().map(|(v, _)| v).sum();
            let nu = welch_satterthwaite(&parts).clamp(1.0, f64::from(MAX_DOF));
            let u = var.sqrt();
            abs.latest = Some((d, u, nu));
            if abs.looks.due(abs.count) && abs.looks.take(d.abs() / u, nu) {
                abs.suspect_since_ns = abs.first_ns;
            }
        }
        self.observe_relative(o, delta_t, slope_var);
    }

    fn observe_relative(&mut self, o: &GravityObservation, delta_t: f64, slope_var: f64) {
        let r = &mut self.relative;
        let u2 = o.noise_var + self.stability_var;
        let Some(base) = r.baseline else {
            if r.n == 0 {
                r.reference_mps2 = o.magnitude_mps2;
                r.first_ns = Some(o.end_ns);
                // A model that states no temperature coefficients' uncertainty pins the slope.
                r.slope_prior_var =
                    (self.model.thermal.is_some() && slope_var > 0.0).then_some(slope_var);
            }
            let w = 1.0 / u2;
            let y = o.magnitude_mps2 - r.reference_mps2;
            let x = delta_t;
            r.sums[0] += w;
            r.sums[1] += w * x;
            r.sums[2] += w * x * x;
            r.sums[3] += w * y;
            r.sums[4] += w * x * y;
            r.n += 1;
            let span_s = (o.end_ns - r.first_ns.unwrap_or(o.end_ns)) as f64 * 1e-9;
            if r.n >= r.stretches && span_s >= r.span_s {
                r.baseline = Some(fit_baseline(r.reference_mps2, &r.sums, r.slope_prior_var));
            }
            return;
        };
        let x = [1.0, delta_t];
        let mut prediction_var = 0.0;
        for i in 0..2 {
            for j in 0..2 {
                prediction_var += x[i] * base.cov[i][j] * x[j];
            }
        }
        let predicted = base.reference_mps2 + base.theta[0] + base.theta[1] * delta_t;
        let d = o.magnitude_mps2 - predicted;
        let u = (u2 + prediction_var).sqrt();
        let z = d / u;
        let delta = r.shift_mps2 / u;
        r.seq.update(
            delta * (z - delta / 2.0),
            delta * (-z - delta / 2.0),
            o.end_ns,
        );
        let (up, down) = r.seq.sides();
        let w = 1.0 / u2;
        for (side, value) in [(&mut r.up, up), (&mut r.down, down)] {
            if value > 0.0 {
                side.0 += w;
                side.1 += w * d;
            } else {
                *side = (0.0, 0.0);
            }
        }
        r.latest = Some((d, u));
        r.prediction_var = prediction_var;
    }

    pub fn stretches(&self) -> u64 {
        self.stretches
    }

    pub fn absolute_report(&self) -> TestReport {
        let Some(abs) = &self.absolute else {
            return TestReport::unjudged(Unjudged::NoLocalGravity);
        };
        let Some((d, u, _)) = abs.latest else {
            return TestReport::unjudged(Unjudged::NoQuietStretch);
        };
        let judged = abs.looks.taken() > 0;
        let verdict = if abs.suspect_since_ns.is_some() {
            Verdict::Suspect
        } else if abs.looks.watch() {
            Verdict::Watch
        } else {
            Verdict::Ok
        };
        TestReport {
            verdict,
            judged,
            statistic: d,
            uncertainty: u,
            since_ns: (verdict != Verdict::Ok).then_some(abs.first_ns).flatten(),
            evidence_nats: 0.0,
            observations: abs.count,
            reason: (!judged).then_some(Unjudged::FewQuietStretches),
            ..TestReport::pending()
        }
    }

    pub fn relative_report(&self) -> TestReport {
        let r = &self.relative;
        let Some((d, u)) = r.latest else {
            // While the baseline is taken, its quiet stretches so far are the evidence.
            return TestReport {
                observations: u64::from(r.n),
                ..TestReport::unjudged(if r.n == 0 {
                    Unjudged::NoQuietStretch
                } else {
                    Unjudged::Baseline
                })
            };
        };
        let side = if r.seq.is_down() { r.down } else { r.up };
        let (statistic, uncertainty) = if side.0 > 0.0 {
            (side.1 / side.0, (1.0 / side.0 + r.prediction_var).sqrt())
        } else {
            (d, u)
        };
        TestReport {
            verdict: r.seq.verdict(),
            judged: true,
            statistic,
            uncertainty,
            since_ns: r.seq.since_ns(),
            evidence_nats: r.seq.value(),
            observations: r.seq.observations(),
            reason: None,
            ..TestReport::pending()
        }
    }

    /// Whether the relative test's baseline is complete.
    pub fn has_baseline(&self) -> bool {
        self.relative.baseline.is_some()
    }
}

/// The weighted least-squares line through the baseline's sums `Σw, Σwx, Σwx², Σwy, Σwxy`,
/// with the prior `N(0, prior_var)` on the slope, or the slope pinned at 0 without one.
fn fit_baseline(reference_mps2: f64, sums: &[f64; 5], prior_var: Option<f64>) -> Baseline {
    let [sw, swx, swxx, swy, swxy] = *sums;
    match prior_var {
        Some(p) => {
            let a = [[sw, swx], [swx, swxx + 1.0 / p]];
            let det = a[0][0] * a[1][1] - a[0][1] * a[1][0];
            let inv = [
                [a[1][1] / det, -a[0][1] / det],
                [-a[1][0] / det, a[0][0] / det],
            ];
            let theta = [
                inv[0][0] * swy + inv[0][1] * swxy,
                inv[1][0] * swy + inv[1][1] * swxy,
            ];
            Baseline {
                reference_mps2,
                theta,
                cov: inv,
            }
        }
        None => Baseline {
            reference_mps2,
            theta: [swy / sw, 0.0],
            cov: [[1.0 / sw, 0.0], [0.0, 0.0]],
        },
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use nalgebra::{Matrix3, SMatrix, Vector3};
    use triax_calibration::corrector::Corrector;
    use triax_protocol::record::{sample, TemperatureModel};

    /// A record with S = diag(0.1) V per m/s², q = 0 and the given static covariance.
    fn diagonal_record(covariance: [[f64; 12]; 12]) -> CalibrationRecord {
        let mut r = sample::record("hand", 1);
        for set in [&mut r.static_set, &mut r.dynamic] {
            set.sensitivity = [[0.1, 0.0, 0.0], [0.0, 0.1, 0.0], [0.0, 0.0, 0.1]];
            set.offset = [0.0; 3];
            set.uncertainty_mps2 = [0.0; 3];
            set.covariance = Some(Box::new(covariance));
        }
        r
    }

    fn model(r: &CalibrationRecord) -> StaticModel {
        let c = Corrector::from_record(r).unwrap();
        StaticModel::new(r, c.set(SetKind::Static))
    }

    /// Gravity along z through S = diag(0.1): a′_z = 9.81, ∂a_z/∂S₂₂ = −9.81/0.1 = −98.1,
    /// ∂a_z/∂q₂ = 1. With σ(S₂₂) = 10⁻⁵, σ(q₂) = 10⁻³ and ρ = ½:
    /// u² = 98.1²·10⁻¹⁰ + 10⁻⁶ − 2·98.1·½·10⁻⁸ = 9.8136·10⁻⁷ (m/s²)².
    #[test]
    fn calibration_variance_along_gravity_by_hand() {
        let mut cov = [[0.0; 12]; 12];
        cov[8][8] = 1e-10;
        cov[11][11] = 1e-6;
        cov[8][11] = 0.5 * 1e-5 * 1e-3;
        cov[11][8] = cov[8][11];
        let m = model(&diagonal_record(cov));
        let (param, stated) = m.calibration_var([0.0, 0.0, 1.0], [0.0, 0.0, 0.981]);
        assert!((param / 9.8136e-7 - 1.0).abs() < 1e-6, "{param:e}");
        assert_eq!(stated, 0.0);
    }

    /// Along a tilted direction with a full random covariance and cross-axis terms: the
    /// corrector's propagation projected on n̂ against nᵀ·J·Σ·Jᵀ·n built here in f64.
    #[test]
    fn calibration_variance_along_any_direction_matches_the_jacobian() {
        let mut cov = SMatrix::<f64, 12, 12>::from_fn(|i, j| ((i * 7 + j * 3) % 11) as f64 - 5.0);
        cov = cov * cov.transpose() * 1e-9;
        let mut rows = [[0.0; 12]; 12];
        for (i, row) in rows.iter_mut().enumerate() {
            for (j, cell) in row.iter_mut().enumerate() {
                *cell = 0.5 * (cov[(i, j)] + cov[(j, i)]);
            }
        }
        let mut r = diagonal_record(rows);
        r.static_set.sensitivity = [
            [0.098, 0.003, -0.002],
            [0.001, 0.103, 0.004],
            [-0.003, 0.002, 0.095],
        ];
        r.static_set.offset = [0.2, -0.1, 0.05];
        let m = model(&r);
        let s = Matrix3::from_fn(|i, j| r.static_set.sensitivity[i][j]);
        let s_inv = s.try_inverse().unwrap();
        let a = Vector3::new(1.5, -2.0, 9.5);
        let v = s * (a - Vector3::from(r.static_set.offset));
        let scaled = s_inv * v;
        let mut j = SMatrix::<f64, 3, 12>::zeros();
        for k in 0..3 {
            for i in 0..3 {
                for l in 0..3 {
                    j[(k, 3 * i + l)] = -s_inv[(k, i)] * scaled[l];
                }
            }
            j[(k, 9 + k)] = 1.0;
        }
        let n = a / a.norm();
        let sigma = SMatrix::<f64, 12, 12>::from_fn(|i, k| rows[i][k]);
        let direct = (n.transpose() * j * sigma * j.transpose() * n)[(0, 0)];
        let (param, _) = m.calibration_var(n.into(), v.into());
        // The corrector keeps its forms in f32.
        assert!(
            (param / direct - 1.0).abs() < 1e-5,
            "{param:e} vs {direct:e}"
        );
    }

    /// Temperature coefficients along z with S = diag(0.1) at V = (0, 0, 0.981): g =
    /// (0, 0, 1, 0, 0, −9.81), so σ²_β = Var(c_q,z) + 9.81²·Var(c_g,z) = 10⁻⁸ + 96.24·10⁻¹⁰.
    #[test]
    fn thermal_slope_variance_by_hand() {
        let mut r = diagonal_record([[0.0; 12]; 12]);
        let mut t = [[0.0; 6]; 6];
        t[2][2] = 1e-8;
        t[5][5] = 1e-10;
        r.temperature = Some(TemperatureModel {
            reference_c: 20.0,
            range_c: [10.0, 30.0],
            offset_mps2_per_c: [0.0; 3],
            gain_per_c: Some([0.0; 3]),
            covariance: t,
            covariance_dof: Some(10.0),
        });
        let m = model(&r);
        let var = m.thermal_slope_var([0.0, 0.0, 1.0], [0.0, 0.0, 0.981], 0.0);
        assert!(
            (var - (1e-8 + 9.81f64.powi(2) * 1e-10)).abs() < 1e-20,
            "{var:e}"
        );
        // The corrector at 30 °C adds ΔT²·σ²_β along z to the parameter part: the same number
        // from its own forms.
        let c = Corrector::from_record(&r).unwrap();
        let warm = c.set(SetKind::Static).at_temperature(30.0).unwrap();
        let cold = c.set(SetKind::Static);
        let v = [0.0, 0.0, 0.981];
        let added = warm.covariance_filtered_parts(v, 0.0, [0.0; 3]).parameters[2][2]
            - cold.covariance_filtered_parts(v, 0.0, [0.0; 3]).parameters[2][2];
        assert!((added / (100.0 * var) - 1.0).abs() < 1e-5, "{added:e}");
    }

    /// The line through (ΔT, y) = (−1, 1), (0, 2), (1, 3) with unit weights and a prior so
    /// wide it does not matter: intercept 2, slope 1, variances 1/3 and 1/2. With a prior of
    /// variance ½ on the slope the normal equations become [[3, 0], [0, 4]]: slope ½.
    #[test]
    fn baseline_line_by_hand() {
        let sums = [3.0, 0.0, 2.0, 6.0, 2.0];
        let b = fit_baseline(9.8, &sums, Some(1e12));
        assert!((b.theta[0] - 2.0).abs() < 1e-9 && (b.theta[1] - 1.0).abs() < 1e-9);
        assert!((b.cov[0][0] - 1.0 / 3.0).abs() < 1e-9 && (b.cov[1][1] - 0.5).abs() < 1e-9);
        let b = fit_baseline(9.8, &sums, Some(0.5));
        assert!((b.theta[1] - 0.5).abs() < 1e-12, "{b:?}");
        let b = fit_baseline(9.8, &sums, None);
        assert_eq!(b.theta, [2.0, 0.0]);
    }
}
