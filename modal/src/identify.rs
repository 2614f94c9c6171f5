//! One window in, the building's modes out: [`identify`].

use nalgebra::Complex;
use serde::{Deserialize, Serialize};

use crate::checks::{check_model, CheckOptions, SensorCheck};
use crate::error::ModalError;
use crate::model::{BuildingModel, Direction};
use crate::ssi::{
    largest_component, mac, noise_floor, normalise, toeplitz_of, Correlations, Pole, Subspace,
};
use crate::stabilisation::{classify, select, DiagramPole, Selected, SelectionCriteria};
use crate::uncertainty::{chain_variances, combine, jackknife_variance, Estimate};
use crate::window::{ChannelId, ChannelOptions, Channels, Window};

/// Settings of an identification. The defaults suit buildings of a few to a few tens of storeys
/// sampled at 50–200 Hz.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SsiConfig {
    pub channels: ChannelOptions,
    /// Lowest frequency a mode may have, Hz.
    pub min_frequency_hz: f64,
    /// Reference channels by sensor and direction; every channel when empty.
    pub references: Vec<ChannelId>,
    /// Block rows `i` of the Toeplitz matrix; when absent, enough for the largest order and
    /// for lags spanning `lag_span_s`.
    pub block_rows: Option<usize>,
    /// Time the lags `1..i` should span when `block_rows` is absent, s.
    pub lag_span_s: f64,
    /// Block columns of the Toeplitz matrix; when absent, as many as block rows. Fewer cost
    /// less (the SVD of each jackknife replicate is the cost of a window) and bias damping
    /// upwards (BENCHMARKS.md: 8 columns instead of 25 doubled the fundamentals' damping bias
    /// on the ten-storey building); at least enough for the largest order.
    pub block_columns: Option<usize>,
    /// The diagram's orders: `min_order, min_order + order_step, …, max_order`; `max_order`
    /// absent: from the data ([`AUTO_ORDER_FACTOR`] times the signal rank, grown while the
    /// selected modes still change, see [`identify`]).
    pub min_order: usize,
    pub max_order: Option<usize>,
    pub order_step: usize,
    /// Blocks of the window for the jackknife (at least 10).
    pub blocks: usize,
    pub selection: SelectionCriteria,
    /// Coverage probability of every stated interval.
    pub coverage_probability: f64,
    /// A replicate's pole matches the mode when its MAC with the mode's shape is at least this
    /// and its frequency within `jackknife_frequency_tolerance`.
    pub jackknife_mac_min: f64,
    pub jackknife_frequency_tolerance: f64,
    /// The building model's checks against the data ([`crate::checks`]).
    pub checks: CheckOptions,
}

impl Default for SsiConfig {
    fn default() -> Self {
        SsiConfig {
            channels: ChannelOptions::default(),
            min_frequency_hz: 0.2,
            references: Vec::new(),
            block_rows: None,
            lag_span_s: 1.0,
            block_columns: None,
            min_order: 4,
            max_order: None,
            order_step: 2,
            blocks: 12,
            selection: SelectionCriteria::default(),
            coverage_probability: 0.95,
            jackknife_mac_min: 0.8,
            jackknife_frequency_tolerance: 0.05,
            checks: CheckOptions::default(),
        }
    }
}

/// One component of a mode shape: the motion of one sensor along one direction of the
/// building, relative to the shape's reference component (which is exactly 1).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ShapeComponent {
    pub sensor_id: String,
    pub direction: Direction,
    /// In-phase part (the amplitude of a classically damped mode).
    pub real: Estimate,
    /// Quadrature part (zero for a classically damped mode; non-zero from noise, time-stamp
    /// errors or non-proportional damping).
    pub imag: Estimate,
    /// The measurement chain's share of the variance of `real` and `imag`.
    pub chain_variance_real: f64,
    pub chain_variance_imag: f64,
}

/// An identified mode.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Mode {
    pub frequency_hz: Estimate,
    pub damping_ratio: Estimate,
    pub shape: Vec<ShapeComponent>,
    /// Index in `shape` of the component the shape is normalised to.
    pub reference_component: usize,
    /// Direction carrying most of the shape's energy.
    pub direction: Direction,
    /// Model order of the representative pole, and how many orders the mode was stable at.
    pub order: usize,
    pub stable_orders: usize,
    /// Jackknife replicates in which the mode was found (out of the blocks).
    pub replicates: usize,
}

impl Mode {
    /// The shape's values (real + i·imag) in channel order: the identified complex shape,
    /// quadrature part included.
    pub fn shape_values(&self) -> Vec<Complex<f64>> {
        self.shape
            .iter()
            .map(|c| Complex::new(c.real.value, c.imag.value))
            .collect()
    }

    /// The mode shape: each component's in-phase part relative to the reference component
    /// (`real`), as complex numbers with zero imaginary part so that [`crate::ssi::mac`]
    /// takes them. This is the shape the mode is compared, tracked and reported by: a
    /// building's damping is close to classical, so its true shapes are real (every point
    /// moves in or against phase), and a quadrature part in an estimate is error, most of
    /// it, for two close modes, each one's leakage into the other (their mixing comes with
    /// a complex coefficient; ARCHITECTURE.md, "Building modes"). `imag` stays reported
    /// with its uncertainty: a quadrature part well beyond it says the building is not
    /// classically damped, or a node's time stamps are off.
    pub fn shape_in_phase(&self) -> Vec<Complex<f64>> {
        self.shape
            .iter()
            .map(|c| Complex::new(c.real.value, 0.0))
            .collect()
    }
}

/// A mode that was selected but could not be given an uncertainty (found in too few
/// replicates): reported for the diagram, never for tracking.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct UnquantifiedMode {
    pub frequency_hz: f64,
    pub damping_ratio: f64,
    pub replicates: usize,
}

/// The result of one window.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Identification {
    pub start_timestamp_ns: i64,
    pub duration_s: f64,
    /// Rate the identification ran at, after decimation, Hz.
    pub sample_rate_hz: f64,
    pub channels: Vec<ChannelId>,
    pub valid_fraction: Vec<f64>,
    pub block_rows: usize,
    pub block_columns: usize,
    pub blocks: usize,
    /// Singular values of the square Toeplitz matrix above its estimation noise
    /// ([`crate::ssi::noise_floor`]): the order the data resolve.
    pub signal_rank: usize,
    pub noise_floor: f64,
    /// The diagram's largest order.
    pub max_order: usize,
    pub modes: Vec<Mode>,
    pub unquantified: Vec<UnquantifiedMode>,
    pub diagram: Vec<DiagramPole>,
    /// What the caller should know about how far to trust the window's modes.
    pub warnings: Vec<IdentificationWarning>,
    /// The building model checked against the window, per sensor ([`crate::checks`]).
    pub checks: Vec<SensorCheck>,
}

/// Something about an identification that its modes alone do not say.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum IdentificationWarning {
    /// The modes selected over the diagram's orders differ from those of its first three
    /// quarters: the diagram had not settled by `max_order` (the order cap was reached, or the
    /// order was configured). The modes that only the higher orders gave, and those they lost.
    NotStabilised {
        max_order: usize,
        appeared_hz: Vec<f64>,
        vanished_hz: Vec<f64>,
    },
    /// No singular value of the Toeplitz matrix rose above its estimation noise: the window
    /// holds no resolvable vibration (a still building, or noise alone).
    NoSignal {
        noise_floor: f64,
        largest_singular_value: f64,
    },
}

impl std::fmt::Display for IdentificationWarning {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let list = |v: &[f64]| {
            if v.is_empty() {
                "none".to_string()
            } else {
                v.iter()
                    .map(|x| format!("{x:.4} Hz"))
                    .collect::<Vec<_>>()
                    .join(", ")
            }
        };
        match self {
            IdentificationWarning::NotStabilised {
                max_order,
                appeared_hz,
                vanished_hz,
            } => write!(
                f,
                "the stabilisation diagram had not settled by order {max_order}: modes found \
                 only above three quarters of it: {}; lost there: {}",
                list(appeared_hz),
                list(vanished_hz)
            ),
            IdentificationWarning::NoSignal {
                noise_floor,
                largest_singular_value,
            } => write!(
                f,
                "no vibration above the estimation noise (largest singular value {largest_singular_value:.3e}, \
                 noise {noise_floor:.3e}): nothing to identify"
            ),
        }
    }
}

/// The diagram's largest order when it is not configured: this many times the signal rank
/// (the order the data resolve), so that each mode is stable over a range of orders above the
/// one that first resolves it, and at least [`AUTO_ORDER_MIN`].
pub const AUTO_ORDER_FACTOR: usize = 2;
pub const AUTO_ORDER_MIN: usize = 20;

/// The frequencies of the modes of `a` with no match in `b`, and of `b` with none in `a`
/// (a match: within the cluster tolerance in frequency, at the cluster MAC or above).
fn difference(
    a: &[Selected],
    b: &[Selected],
    criteria: &SelectionCriteria,
) -> (Vec<f64>, Vec<f64>) {
    let matches = |p: &Pole, q: &Pole| {
        (p.frequency_hz - q.frequency_hz).abs()
            <= criteria.cluster_frequency_tolerance * q.frequency_hz
            && mac(&p.shape, &q.shape) >= criteria.cluster_mac_min
    };
    let missing = |from: &[Selected], other: &[Selected]| -> Vec<f64> {
        from.iter()
            .filter(|s| !other.iter().any(|o| matches(&s.pole, &o.pole)))
            .map(|s| s.pole.frequency_hz)
            .collect()
    };
    (missing(a, b), missing(b, a))
}

/// Identifies the building's modes in one window: channels ([`Channels::from_window`]),
/// correlations per block, SSI-COV over the diagram's orders, selection, then the jackknife
/// and the measurement chain for the uncertainty of every selected mode.
pub fn identify(
    model: &BuildingModel,
    window: &Window,
    config: &SsiConfig,
) -> Result<Identification, ModalError> {
    model.validate()?;
    config.validate()?;
    let channels = Channels::from_window(model, window, &config.channels)?;
    let l = channels.ids.len();
    let references: Vec<usize> =
        if config.references.is_empty() {
            (0..l).collect()
        } else {
            config
                .references
                .iter()
                .map(|id| {
                    channels.ids.iter().position(|c| c == id).ok_or_else(|| {
                        ModalError::InvalidOption {
                            field: "references",
                            reason: format!("{} {:?} is not a channel", id.sensor_id, id.direction),
                        }
                    })
                })
                .collect::<Result<_, _>>()?
        };
    let r = references.len();
    let fs = channels.sample_rate_hz;
    let block_rows = config.block_rows.unwrap_or_else(|| {
        let for_order = config.max_order.map_or(0, |m| m.div_ceil(l.min(r)) + 1);
        let for_span = (config.lag_span_s * fs).ceil() as usize;
        for_order.max(for_span).max(2)
    });
    // Lags for the square Toeplitz matrix, whose singular values say the order.
    let correlations =
        Correlations::compute(&channels, &references, 2 * block_rows - 1, config.blocks)?;
    let full = correlations.matrices(None)?;
    let square = toeplitz_of(&full, block_rows, block_rows);
    let floor = noise_floor(&correlations, block_rows, block_rows)?;
    let singular_values = {
        let mut v: Vec<f64> = square
            .svd(false, false)
            .singular_values
            .iter()
            .copied()
            .collect();
        v.sort_by(|a, b| b.total_cmp(a));
        v
    };
    let signal_rank = singular_values.iter().filter(|&&v| v > floor).count();
    let rank_cap = (l * (block_rows - 1)).min(r * block_rows);
    let (mut max_order, order_cap) = match config.max_order {
        Some(m) => (m.min(rank_cap), m.min(rank_cap)),
        None => {
            let initial = (AUTO_ORDER_FACTOR * signal_rank).max(AUTO_ORDER_MIN);
            (
                initial.min(rank_cap),
                (3 * initial / 2).max(initial).min(rank_cap),
            )
        }
    };
    let block_columns = config
        .block_columns
        .unwrap_or(block_rows)
        .max(order_cap.div_ceil(r) + 1)
        .min(block_rows);
    let subspace = Subspace::new(
        &toeplitz_of(&full, block_rows, block_columns),
        l,
        order_cap,
        fs,
    )?;
    let order_cap = order_cap.min(subspace.max_order());
    max_order = max_order.min(order_cap);
    let band = (config.min_frequency_hz, config.channels.max_frequency_hz);
    let mut warnings = Vec::new();
    if signal_rank == 0 {
        warnings.push(IdentificationWarning::NoSignal {
            noise_floor: floor,
            largest_singular_value: singular_values.first().copied().unwrap_or(0.0),
        });
    }
    // The scan: orders up to `max_order`, grown by half while the modes selected from it
    // differ from those of its first three quarters, up to `order_cap`.
    let mut orders: Vec<usize> = Vec::new();
    let mut poles: Vec<Vec<Pole>> = Vec::new();
    let (marks, selected) = loop {
        for n in (config.min_order..=max_order).step_by(config.order_step) {
            if orders.last().is_none_or(|&last| n > last) {
                orders.push(n);
                poles.push(subspace.poles(n)?);
            }
        }
        let marks = classify(&poles, &config.selection);
        let selected = select(&poles, &marks, &config.selection, band);
        let part = orders.iter().filter(|&&n| 4 * n <= 3 * max_order).count();
        let earlier = select(&poles[..part], &marks[..part], &config.selection, band);
        let (appeared, vanished) = difference(&selected, &earlier, &config.selection);
        if appeared.is_empty() && vanished.is_empty() {
            break (marks, selected);
        }
        if max_order >= order_cap || config.max_order.is_some() {
            warnings.push(IdentificationWarning::NotStabilised {
                max_order,
                appeared_hz: appeared,
                vanished_hz: vanished,
            });
            break (marks, selected);
        }
        max_order = (3 * max_order / 2).min(order_cap);
    };
    let diagram = poles
        .iter()
        .zip(&marks)
        .flat_map(|(ps, ms)| ps.iter().zip(ms))
        .map(|(p, &s)| DiagramPole {
            order: p.order,
            frequency_hz: p.frequency_hz,
            damping_ratio: p.damping_ratio,
            stability: s,
        })
        .collect();

    // Jackknife: per left-out block, the system at each order a selected mode was taken at.
    let mut needed: Vec<usize> = selected.iter().map(|s| s.pole.order).collect();
    needed.sort_unstable();
    needed.dedup();
    let max_needed = needed.last().copied().unwrap_or(config.min_order);
    let mut replicates: Vec<Vec<Option<Pole>>> = vec![Vec::new(); selected.len()];
    for block in 0..config.blocks {
        let matrices = correlations.matrices(Some(block))?;
        let sub = Subspace::new(
            &toeplitz_of(&matrices, block_rows, block_columns),
            l,
            max_needed,
            fs,
        )?;
        let mut by_order = Vec::with_capacity(needed.len());
        for &n in &needed {
            by_order.push((n, sub.poles(n)?));
        }
        for (mode, s) in selected.iter().enumerate() {
            let candidates = by_order
                .iter()
                .find(|(n, _)| *n == s.pole.order)
                .map_or(&[][..], |(_, p)| p.as_slice());
            replicates[mode].push(best_match(&s.pole, candidates, config));
        }
    }

    let dof = (config.blocks - 1) as f64;
    let p = config.coverage_probability;
    let mut modes = Vec::new();
    let mut unquantified = Vec::new();
    for (s, reps) in selected.iter().zip(&replicates) {
        let found: Vec<&Pole> = reps.iter().flatten().collect();
        if found.len() < config.blocks {
            unquantified.push(UnquantifiedMode {
                frequency_hz: s.pole.frequency_hz,
                damping_ratio: s.pole.damping_ratio,
                replicates: found.len(),
            });
            continue;
        }
        let frequencies: Vec<f64> = found.iter().map(|p| p.frequency_hz).collect();
        let dampings: Vec<f64> = found.iter().map(|p| p.damping_ratio).collect();
        let reference = largest_component(&s.pole.shape);
        let shape = normalise(&s.pole.shape, reference);
        let rep_shapes: Vec<Vec<Complex<f64>>> = found
            .iter()
            .map(|p| normalise(&p.shape, reference))
            .collect();
        let chain = chain_variances(&channels, &s.pole.shape, reference, s.pole.frequency_hz);
        let components = shape
            .iter()
            .enumerate()
            .map(|(c, value)| {
                let re: Vec<f64> = rep_shapes.iter().map(|v| v[c].re).collect();
                let im: Vec<f64> = rep_shapes.iter().map(|v| v[c].im).collect();
                let (chain_re, chain_im, chain_dof) = chain[c];
                ShapeComponent {
                    sensor_id: channels.ids[c].sensor_id.clone(),
                    direction: channels.ids[c].direction,
                    real: combine(
                        value.re,
                        jackknife_variance(&re),
                        dof,
                        chain_re,
                        chain_dof,
                        p,
                    ),
                    imag: combine(
                        value.im,
                        jackknife_variance(&im),
                        dof,
                        chain_im,
                        chain_dof,
                        p,
                    ),
                    chain_variance_real: chain_re,
                    chain_variance_imag: chain_im,
                }
            })
            .collect();
        modes.push(Mode {
            frequency_hz: Estimate::new(
                s.pole.frequency_hz,
                jackknife_variance(&frequencies).sqrt(),
                dof,
                p,
            ),
            damping_ratio: Estimate::new(
                s.pole.damping_ratio,
                jackknife_variance(&dampings).sqrt(),
                dof,
                p,
            ),
            shape: components,
            reference_component: reference,
            direction: dominant_direction(&channels.ids, &shape),
            order: s.pole.order,
            stable_orders: s.cluster_size,
            replicates: found.len(),
        });
    }

    let checks = check_model(
        model,
        window,
        &channels,
        &modes,
        config.blocks,
        &config.checks,
    );
    Ok(Identification {
        start_timestamp_ns: window.start_timestamp_ns,
        duration_s: window.duration_s(),
        sample_rate_hz: fs,
        channels: channels.ids.clone(),
        valid_fraction: channels.valid_fraction.clone(),
        block_rows,
        block_columns,
        blocks: config.blocks,
        signal_rank,
        noise_floor: floor,
        max_order,
        modes,
        unquantified,
        diagram,
        warnings,
        checks,
    })
}

impl SsiConfig {
    /// Checks every setting, naming the first that is wrong (as `channels.max_frequency_hz`,
    /// `selection.mac_min`, …). [`identify`] calls it; a service calls it when it reads its
    /// configuration, so that a mistake stops it at start rather than at its first window.
    pub fn validate(&self) -> Result<(), ModalError> {
        let bad = |field: &'static str, reason: &str| {
            Err(ModalError::InvalidOption {
                field,
                reason: reason.to_string(),
            })
        };
        let unit = |v: f64| v > 0.0 && v <= 1.0;
        let share = |v: f64| v > 0.0 && v < 1.0;
        let c = &self.channels;
        if c.directions.is_empty() {
            return bad("channels.directions", "at least one direction");
        }
        if (1..c.directions.len()).any(|i| c.directions[..i].contains(&c.directions[i])) {
            return bad("channels.directions", "a direction is listed twice");
        }
        if !(c.max_frequency_hz.is_finite() && c.max_frequency_hz > 0.0) {
            return bad(
                "channels.max_frequency_hz",
                "must be a positive number of Hz",
            );
        }
        if !unit(c.min_valid_fraction) {
            return bad("channels.min_valid_fraction", "must be in (0, 1]");
        }
        if !(self.min_frequency_hz >= 0.0 && self.min_frequency_hz < c.max_frequency_hz) {
            return bad(
                "min_frequency_hz",
                "must be ≥ 0 and below channels.max_frequency_hz",
            );
        }
        if self
            .block_rows
            .is_some_and(|v| !(2..=MAX_BLOCK_ROWS).contains(&v))
        {
            return bad("block_rows", "must be in [2, 1000]");
        }
        if self
            .block_columns
            .is_some_and(|v| !(1..=MAX_BLOCK_ROWS).contains(&v))
        {
            return bad("block_columns", "must be in [1, 1000]");
        }
        if !(self.lag_span_s.is_finite() && self.lag_span_s > 0.0 && self.lag_span_s <= 60.0) {
            return bad("lag_span_s", "must be in (0, 60] s");
        }
        if self.min_order < 2 {
            return bad("min_order", "must be ≥ 2");
        }
        if self.order_step == 0 {
            return bad("order_step", "must be ≥ 1");
        }
        if self
            .max_order
            .is_some_and(|m| m < self.min_order || m > MAX_ORDER)
        {
            return bad("max_order", "must be in [min_order, 2000]");
        }
        if !(10..=1000).contains(&self.blocks) {
            return bad(
                "blocks",
                "must be in [10, 1000]: at least 10 so that the jackknife's variance has 9 \
                 degrees of freedom",
            );
        }
        if !(self.coverage_probability > 0.5 && self.coverage_probability < 1.0) {
            return bad("coverage_probability", "must be in (0.5, 1)");
        }
        if !unit(self.jackknife_mac_min) {
            return bad("jackknife_mac_min", "must be in (0, 1]");
        }
        if !share(self.jackknife_frequency_tolerance) {
            return bad("jackknife_frequency_tolerance", "must be in (0, 1)");
        }
        let s = &self.selection;
        if !share(s.frequency_tolerance) {
            return bad("selection.frequency_tolerance", "must be in (0, 1)");
        }
        if !(s.damping_tolerance.is_finite() && s.damping_tolerance > 0.0) {
            return bad("selection.damping_tolerance", "must be > 0");
        }
        if !unit(s.mac_min) {
            return bad("selection.mac_min", "must be in (0, 1]");
        }
        if !(s.damping_ratio_min >= 0.0 && s.damping_ratio_min < s.damping_ratio_max) {
            return bad(
                "selection.damping_ratio_min",
                "must be ≥ 0 and below selection.damping_ratio_max",
            );
        }
        if s.damping_ratio_max.is_nan() || s.damping_ratio_max > 1.0 {
            return bad("selection.damping_ratio_max", "must be ≤ 1");
        }
        if !share(s.cluster_frequency_tolerance) {
            return bad("selection.cluster_frequency_tolerance", "must be in (0, 1)");
        }
        if !unit(s.cluster_mac_min) {
            return bad("selection.cluster_mac_min", "must be in (0, 1]");
        }
        if !unit(s.min_cluster_share) {
            return bad("selection.min_cluster_share", "must be in (0, 1]");
        }
        let m = self.checks.mounting_tolerance_deg;
        if !(m.is_finite() && (0.0..=90.0).contains(&m)) {
            return bad(
                "checks.mounting_tolerance_deg",
                "must be in [0, 90] degrees",
            );
        }
        Ok(())
    }
}

/// The largest `block_rows`, `block_columns` and `max_order` accepted: a Toeplitz matrix of
/// a thousand block rows of a dozen channels is already gigabytes.
pub const MAX_BLOCK_ROWS: usize = 1000;
pub const MAX_ORDER: usize = 2000;

/// The replicate's pole that is the mode: the best MAC among poles within the frequency
/// tolerance, if good enough.
fn best_match(mode: &Pole, candidates: &[Pole], config: &SsiConfig) -> Option<Pole> {
    candidates
        .iter()
        .filter(|p| {
            (p.frequency_hz - mode.frequency_hz).abs()
                <= config.jackknife_frequency_tolerance * mode.frequency_hz
        })
        .map(|p| (mac(&p.shape, &mode.shape), p))
        .filter(|(m, _)| *m >= config.jackknife_mac_min)
        .max_by(|a, b| a.0.total_cmp(&b.0))
        .map(|(_, p)| p.clone())
}

fn dominant_direction(ids: &[ChannelId], shape: &[Complex<f64>]) -> Direction {
    let mut energy = [0.0; 3];
    for (id, v) in ids.iter().zip(shape) {
        energy[id.direction.index()] += v.norm_sqr();
    }
    let best = (0..3)
        .max_by(|&a, &b| energy[a].total_cmp(&energy[b]))
        .unwrap_or(0);
    [Direction::X, Direction::Y, Direction::Z][best]
}
