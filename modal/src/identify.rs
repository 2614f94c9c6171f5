//! One window in, the building's modes out: [`identify`].

use nalgebra::Complex;
use serde::{Deserialize, Serialize};

use crate::error::ModalError;
use crate::model::{BuildingModel, Direction};
use crate::ssi::{largest_component, mac, normalise, toeplitz, Correlations, Pole, Subspace};
use crate::stabilisation::{classify, select, DiagramPole, SelectionCriteria};
use crate::uncertainty::{chain_variances, combine, jackknife_variance, Estimate};
use crate::window::{ChannelId, ChannelOptions, Channels, Window};

/// Settings of an identification. The defaults suit buildings of a few to a few tens of storeys
/// sampled at 50–200 Hz.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default)]
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
    /// The diagram's orders: `min_order, min_order + order_step, …, max_order`.
    pub min_order: usize,
    pub max_order: usize,
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
}

impl Default for SsiConfig {
    fn default() -> Self {
        SsiConfig {
            channels: ChannelOptions::default(),
            min_frequency_hz: 0.2,
            references: Vec::new(),
            block_rows: None,
            lag_span_s: 1.0,
            min_order: 4,
            max_order: 40,
            order_step: 2,
            blocks: 12,
            selection: SelectionCriteria::default(),
            coverage_probability: 0.95,
            jackknife_mac_min: 0.8,
            jackknife_frequency_tolerance: 0.05,
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
    pub blocks: usize,
    pub modes: Vec<Mode>,
    pub unquantified: Vec<UnquantifiedMode>,
    pub diagram: Vec<DiagramPole>,
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
    check(config)?;
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
        let for_order = config.max_order.div_ceil(l.min(r)) + 1;
        let for_span = (config.lag_span_s * fs).ceil() as usize;
        for_order.max(for_span).max(2)
    });
    let correlations =
        Correlations::compute(&channels, &references, 2 * block_rows - 1, config.blocks)?;
    let full = correlations.matrices(None)?;
    let subspace = Subspace::new(&toeplitz(&full, block_rows), l, config.max_order, fs)?;

    let orders: Vec<usize> = (config.min_order..=subspace.max_order())
        .step_by(config.order_step)
        .collect();
    let poles: Vec<Vec<Pole>> = orders
        .iter()
        .map(|&n| subspace.poles(n))
        .collect::<Result<_, _>>()?;
    let marks = classify(&poles, &config.selection);
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
    let selected = select(
        &poles,
        &marks,
        &config.selection,
        (config.min_frequency_hz, config.channels.max_frequency_hz),
    );

    // Jackknife: per left-out block, the system at each order a selected mode was taken at.
    let mut needed: Vec<usize> = selected.iter().map(|s| s.pole.order).collect();
    needed.sort_unstable();
    needed.dedup();
    let max_needed = needed.last().copied().unwrap_or(config.min_order);
    let mut replicates: Vec<Vec<Option<Pole>>> = vec![Vec::new(); selected.len()];
    for block in 0..config.blocks {
        let matrices = correlations.matrices(Some(block))?;
        let sub = Subspace::new(&toeplitz(&matrices, block_rows), l, max_needed, fs)?;
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

    Ok(Identification {
        start_timestamp_ns: window.start_timestamp_ns,
        duration_s: window.duration_s(),
        sample_rate_hz: fs,
        channels: channels.ids.clone(),
        valid_fraction: channels.valid_fraction.clone(),
        block_rows,
        blocks: config.blocks,
        modes,
        unquantified,
        diagram,
    })
}

fn check(config: &SsiConfig) -> Result<(), ModalError> {
    let invalid = |field: &'static str, reason: &str| {
        Err(ModalError::InvalidOption {
            field,
            reason: reason.to_string(),
        })
    };
    if config.blocks < 10 {
        return invalid(
            "blocks",
            "at least 10 blocks, so that the jackknife's variance has 9 degrees of freedom",
        );
    }
    if config.min_order < 2 || config.order_step == 0 || config.max_order < config.min_order {
        return invalid(
            "max_order",
            "orders must satisfy 2 ≤ min_order ≤ max_order and order_step ≥ 1",
        );
    }
    if !(config.coverage_probability > 0.5 && config.coverage_probability < 1.0) {
        return invalid("coverage_probability", "must be in (0.5, 1)");
    }
    if !(config.min_frequency_hz >= 0.0
        && config.min_frequency_hz < config.channels.max_frequency_hz)
    {
        return invalid("min_frequency_hz", "must be below max_frequency_hz");
    }
    Ok(())
}

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
