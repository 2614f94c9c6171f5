//! The stabilisation diagram and the automatic choice of physical modes.
//!
//! A physical mode shows up at every model order above the one that first resolves it, at the
//! same frequency, damping and shape; a pole that models noise or the data's finite length
//! wanders with the order. So each pole is compared with the nearest-in-frequency pole of the
//! previous order ([`Stability`]): stable when the frequency moved by less than
//! `frequency_tolerance` (1 %), the damping ratio by less than `damping_tolerance` (5 %,
//! relative) and the shape's MAC is at least `mac_min` (0.98). Stable poles with a damping
//! ratio in the plausible range (0.1 % to 10 % by default: real buildings are in 0.5–5 %, and a
//! pole outside is noise or a harmonic) are then clustered across orders by frequency and
//! shape; a cluster found at a share `min_cluster_share` (25 %) of the orders or more is a
//! mode. Its representative is the cluster's pole nearest the cluster's median frequency, at
//! its own order: the uncertainty is computed for that pole at that order.

use serde::{Deserialize, Serialize};

use crate::ssi::{mac, Pole};

/// How a pole compares with the previous order's.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Stability {
    /// No pole of the previous order within the frequency tolerance.
    New,
    /// Frequency stable only.
    Frequency,
    /// Frequency and damping stable.
    FrequencyDamping,
    /// Frequency and shape stable.
    FrequencyShape,
    /// Frequency, damping and shape stable.
    Stable,
}

/// One point of the stabilisation diagram.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DiagramPole {
    pub order: usize,
    pub frequency_hz: f64,
    pub damping_ratio: f64,
    pub stability: Stability,
}

/// Criteria of stability and selection.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct SelectionCriteria {
    pub frequency_tolerance: f64,
    pub damping_tolerance: f64,
    pub mac_min: f64,
    pub damping_ratio_min: f64,
    pub damping_ratio_max: f64,
    /// Tolerance on frequency for a pole to join a cluster (relative to the cluster's mean).
    pub cluster_frequency_tolerance: f64,
    /// MAC a pole must have with a cluster's first pole to join it.
    pub cluster_mac_min: f64,
    /// Share of the diagram's orders a cluster must be found at.
    pub min_cluster_share: f64,
}

impl Default for SelectionCriteria {
    fn default() -> Self {
        SelectionCriteria {
            frequency_tolerance: 0.01,
            damping_tolerance: 0.05,
            mac_min: 0.98,
            damping_ratio_min: 0.001,
            damping_ratio_max: 0.10,
            cluster_frequency_tolerance: 0.01,
            cluster_mac_min: 0.95,
            min_cluster_share: 0.25,
        }
    }
}

/// Classifies each order's poles against the previous order's.
pub fn classify(orders: &[Vec<Pole>], criteria: &SelectionCriteria) -> Vec<Vec<Stability>> {
    let mut out = Vec::with_capacity(orders.len());
    for (index, poles) in orders.iter().enumerate() {
        let previous: &[Pole] = if index == 0 { &[] } else { &orders[index - 1] };
        out.push(
            poles
                .iter()
                .map(|p| stability(p, previous, criteria))
                .collect(),
        );
    }
    out
}

fn stability(pole: &Pole, previous: &[Pole], criteria: &SelectionCriteria) -> Stability {
    let nearest = previous.iter().min_by(|a, b| {
        (a.frequency_hz - pole.frequency_hz)
            .abs()
            .total_cmp(&(b.frequency_hz - pole.frequency_hz).abs())
    });
    let Some(q) = nearest else {
        return Stability::New;
    };
    let df = (q.frequency_hz - pole.frequency_hz).abs() / pole.frequency_hz;
    if df > criteria.frequency_tolerance {
        return Stability::New;
    }
    let damping_ok = (q.damping_ratio - pole.damping_ratio).abs()
        <= criteria.damping_tolerance * pole.damping_ratio.abs();
    let shape_ok = mac(&q.shape, &pole.shape) >= criteria.mac_min;
    match (damping_ok, shape_ok) {
        (true, true) => Stability::Stable,
        (true, false) => Stability::FrequencyDamping,
        (false, true) => Stability::FrequencyShape,
        (false, false) => Stability::Frequency,
    }
}

/// A selected mode: the representative pole and the cluster's size.
#[derive(Debug, Clone, PartialEq)]
pub struct Selected {
    pub pole: Pole,
    pub cluster_size: usize,
}

/// The physical modes of a diagram, sorted by frequency.
pub fn select(
    orders: &[Vec<Pole>],
    stability: &[Vec<Stability>],
    criteria: &SelectionCriteria,
    frequency_range_hz: (f64, f64),
) -> Vec<Selected> {
    let mut candidates: Vec<&Pole> = orders
        .iter()
        .zip(stability)
        .flat_map(|(poles, marks)| poles.iter().zip(marks))
        .filter(|(p, &s)| {
            s == Stability::Stable
                && p.damping_ratio >= criteria.damping_ratio_min
                && p.damping_ratio <= criteria.damping_ratio_max
                && p.frequency_hz >= frequency_range_hz.0
                && p.frequency_hz <= frequency_range_hz.1
        })
        .map(|(p, _)| p)
        .collect();
    candidates.sort_by(|a, b| a.frequency_hz.total_cmp(&b.frequency_hz));

    struct Cluster<'a> {
        poles: Vec<&'a Pole>,
        frequency_sum: f64,
    }
    let mut clusters: Vec<Cluster> = Vec::new();
    for pole in candidates {
        let best = clusters
            .iter_mut()
            .filter(|c| {
                let mean = c.frequency_sum / c.poles.len() as f64;
                (pole.frequency_hz - mean).abs() <= criteria.cluster_frequency_tolerance * mean
            })
            .map(|c| {
                let m = mac(&c.poles[0].shape, &pole.shape);
                (m, c)
            })
            .filter(|(m, _)| *m >= criteria.cluster_mac_min)
            .max_by(|a, b| a.0.total_cmp(&b.0));
        match best {
            Some((_, c)) => {
                c.poles.push(pole);
                c.frequency_sum += pole.frequency_hz;
            }
            None => clusters.push(Cluster {
                poles: vec![pole],
                frequency_sum: pole.frequency_hz,
            }),
        }
    }

    let needed = (criteria.min_cluster_share * orders.len() as f64).ceil() as usize;
    let mut selected = Vec::new();
    for cluster in clusters {
        let mut distinct_orders: Vec<usize> = cluster.poles.iter().map(|p| p.order).collect();
        distinct_orders.sort_unstable();
        distinct_orders.dedup();
        if distinct_orders.len() < needed.max(2) {
            continue;
        }
        let mut frequencies: Vec<f64> = cluster.poles.iter().map(|p| p.frequency_hz).collect();
        frequencies.sort_by(f64::total_cmp);
        let median = frequencies[frequencies.len() / 2];
        // A cluster is never empty: it is created with a pole.
        let representative = cluster
            .poles
            .iter()
            .min_by(|a, b| {
                (a.frequency_hz - median)
                    .abs()
                    .total_cmp(&(b.frequency_hz - median).abs())
            })
            .expect("a cluster holds at least one pole");
        selected.push(Selected {
            pole: (*representative).clone(),
            cluster_size: distinct_orders.len(),
        });
    }
    selected.sort_by(|a, b| a.pole.frequency_hz.total_cmp(&b.pole.frequency_hz));
    selected
}
