//! The buildings' modes as the console shows them: each building's last windows from
//! `triax/<building>/modes` (PROTOCOL.md §3.10), kept in memory since the console started, and
//! per building one view (`/api/modes`): per track its frequency trend with the stated band
//! (`value ± k·u`), its environmental baseline and verdicts, and the latest window's modes with
//! their shapes.
//!
//! The modal service keeps the durable record; the console only remembers what it heard, a
//! fortnight of 30-minute windows per building at most ([`MAX_WINDOWS`]) and as many buildings
//! as the fleet view ([`crate::fleet::MAX_BUILDINGS`]; only the watched ones when the console
//! is given a list), and says since when.

use std::collections::{BTreeMap, VecDeque};
use std::sync::{Arc, Mutex};

use serde_json::{json, Value};
use triax_protocol::messages::{BuildingModes, ModalDirection, ModalVerdict};
use triax_protocol::provenance::{verify_with, Freshness};
use triax_protocol::signing::TrustedKeys;
use triax_protocol::{from_json, BuildingId, Key};

/// Windows kept per building: two weeks of 30-minute windows.
pub const MAX_WINDOWS: usize = 672;

/// What the console heard of each building's modes.
#[derive(Debug, Default)]
pub struct ModesBook {
    buildings: BTreeMap<BuildingId, VecDeque<BuildingModes>>,
    /// Buildings to keep; every building (up to the bound) when empty.
    watched: Vec<BuildingId>,
    /// Messages on a modes key that did not decode, or named another building than their key.
    pub malformed: u64,
    /// Windows of buildings beyond [`crate::fleet::MAX_BUILDINGS`], not kept.
    pub dropped: u64,
    /// Whether windows are verified: true when the console trusts alerting keys, which sign
    /// `triax-modes`' windows as they sign its alerts.
    pub verifying: bool,
    /// Windows dropped as not signed by a trusted key (`unsigned`, `unknown_key`, …).
    pub unverified: u64,
}

fn direction(d: ModalDirection) -> &'static str {
    match d {
        ModalDirection::X => "x",
        ModalDirection::Y => "y",
        ModalDirection::Z => "z",
    }
}

fn verdict(v: Option<ModalVerdict>) -> Value {
    match v {
        None => Value::Null,
        Some(ModalVerdict::Training) => json!("training"),
        Some(ModalVerdict::Normal) => json!("normal"),
        Some(ModalVerdict::Possible) => json!("possible"),
        Some(ModalVerdict::Shift) => json!("shift"),
    }
}

/// A finite number as JSON, anything else as null (JSON has no infinity).
fn number(v: f64) -> Value {
    if v.is_finite() {
        json!(v)
    } else {
        Value::Null
    }
}

impl ModesBook {
    /// A book of the `watched` buildings' modes (every building's when empty).
    pub fn new(watched: Vec<BuildingId>) -> ModesBook {
        ModesBook {
            watched,
            ..ModesBook::default()
        }
    }

    /// Takes a message heard on `key`; a repeated window (the service identified it again after
    /// a restart) replaces the one before.
    pub fn on_message(&mut self, key: &str, payload: &[u8]) {
        let parsed = from_json::<BuildingModes>(payload).ok().filter(|m| {
            Key::parse(key)
                .ok()
                .is_some_and(|k| k == Key::Modes(m.building.clone()))
        });
        let Some(modes) = parsed else {
            self.malformed += 1;
            return;
        };
        if !self.watched.is_empty() && !self.watched.contains(&modes.building) {
            return;
        }
        if !self.buildings.contains_key(&modes.building)
            && self.buildings.len() >= crate::fleet::MAX_BUILDINGS
        {
            self.dropped += 1;
            return;
        }
        let windows = self.buildings.entry(modes.building.clone()).or_default();
        if let Some(same) = windows
            .iter_mut()
            .find(|w| w.window_start_ns == modes.window_start_ns)
        {
            *same = modes;
            return;
        }
        let at = windows.partition_point(|w| w.window_start_ns < modes.window_start_ns);
        windows.insert(at, modes);
        while windows.len() > MAX_WINDOWS {
            windows.pop_front();
        }
    }

    /// Buildings with at least one window.
    pub fn buildings(&self) -> Vec<BuildingId> {
        self.buildings.keys().cloned().collect()
    }

    /// The view of one building: `null` fields where nothing was heard.
    pub fn view(&self, building: &BuildingId) -> Value {
        let Some(windows) = self.buildings.get(building) else {
            return json!({"building": building.as_str(), "windows": 0, "tracks": [],
                          "latest": null, "malformed": self.malformed,
                          "verifying": self.verifying, "unverified": self.unverified});
        };
        let mut tracks: BTreeMap<u64, (ModalDirection, Vec<Value>)> = BTreeMap::new();
        for w in windows {
            for m in &w.modes {
                let Some(t) = m.track else { continue };
                let f = &m.frequency_hz;
                tracks
                    .entry(t)
                    .or_insert((m.direction, Vec::new()))
                    .1
                    .push(json!({
                        "start_ns": w.window_start_ns,
                        "end_ns": w.window_end_ns,
                        "frequency_hz": f.value,
                        "expanded_hz": number(f.coverage_factor * f.standard_uncertainty),
                        "predicted_hz": m.predicted_hz,
                        "verdict": verdict(m.verdict),
                        "block_verdict": verdict(m.block_verdict),
                    }));
            }
        }
        let tracks: Vec<Value> = tracks
            .into_iter()
            .map(
                |(t, (d, points))| json!({"track": t, "direction": direction(d), "points": points}),
            )
            .collect();
        // The latest window that was identified (a refused one is said, not shown as empty).
        let latest = windows.iter().rev().find(|w| w.refused.is_none());
        let refused_after = latest.map_or(windows.len(), |l| {
            windows
                .iter()
                .filter(|w| w.window_start_ns > l.window_start_ns)
                .count()
        });
        let last_refusal = windows
            .iter()
            .rev()
            .find_map(|w| w.refused.clone().map(|r| (w.window_start_ns, r)));
        let latest = latest.map(|w| {
            json!({
                "start_ns": w.window_start_ns,
                "end_ns": w.window_end_ns,
                "temperature_c": w.temperature_c,
                "identified_at": w.identified_at.unix_timestamp(),
                "modes": w.modes.iter().map(|m| json!({
                    "track": m.track,
                    "direction": direction(m.direction),
                    "frequency_hz": m.frequency_hz.value,
                    "frequency_expanded_hz": number(m.frequency_hz.coverage_factor * m.frequency_hz.standard_uncertainty),
                    "damping_ratio": m.damping_ratio.value,
                    "damping_expanded": number(m.damping_ratio.coverage_factor * m.damping_ratio.standard_uncertainty),
                    "coverage_probability": m.frequency_hz.coverage_probability,
                    "verdict": verdict(m.verdict),
                    "reference_component": m.reference_component,
                    "shape": m.shape.iter().map(|c| json!({
                        "sensor_id": c.sensor_id.as_str(),
                        "direction": direction(c.direction),
                        "real": c.real.value,
                        "expanded": number(c.real.coverage_factor * c.real.standard_uncertainty),
                    })).collect::<Vec<_>>(),
                })).collect::<Vec<_>>(),
            })
        });
        json!({
            "building": building.as_str(),
            "windows": windows.len(),
            "first_start_ns": windows.front().map(|w| w.window_start_ns),
            "last_end_ns": windows.back().map(|w| w.window_end_ns),
            "tracks": tracks,
            "latest": latest,
            "refused_since_latest": refused_after,
            "last_refusal": last_refusal.map(|(t, r)| json!({"start_ns": t, "reason": r})),
            "malformed": self.malformed,
            "dropped": self.dropped,
            "verifying": self.verifying,
            "unverified": self.unverified,
        })
    }
}

/// Subscribes to every building's modes into `book`; the subscription lasts as long as the
/// returned handle. With `trusted` keys (the alerting keys the console trusts), only a window
/// signed by one of them is kept, and not one signed more than 5 s before the newest.
pub async fn watch(
    session: &zenoh::Session,
    book: &Arc<Mutex<ModesBook>>,
    trusted: TrustedKeys,
) -> zenoh::Result<zenoh::pubsub::Subscriber<()>> {
    let book = book.clone();
    let verifying = !trusted.is_empty();
    book.lock().unwrap_or_else(|p| p.into_inner()).verifying = verifying;
    let fresh = Mutex::new(Freshness::default());
    session
        .declare_subscriber("triax/*/modes")
        .callback(move |sample| {
            let payload = sample.payload().to_bytes();
            let key = sample.key_expr().as_str();
            let checked = match verifying {
                false => Ok(()),
                true => {
                    let attachment = sample.attachment().map(|a| a.to_bytes());
                    verify_with(trusted.keys(), key, "", &payload, attachment.as_deref()).and_then(
                        |s| {
                            fresh
                                .lock()
                                .unwrap_or_else(|p| p.into_inner())
                                .check(key, s.signed_at_ns)
                        },
                    )
                }
            };
            // A poisoned lock means a panic mid-update elsewhere: keep serving what is there.
            let mut b = book.lock().unwrap_or_else(|p| p.into_inner());
            match checked {
                Ok(()) => b.on_message(key, &payload),
                Err(e) => {
                    tracing::debug!(key, cause = %e, "modes window not verified, dropped");
                    b.unverified += 1;
                }
            }
        })
        .await
}

#[cfg(test)]
mod tests {
    use super::*;
    use time::OffsetDateTime;

    fn window(building: &str, start_ns: i64) -> Vec<u8> {
        triax_protocol::to_json(&BuildingModes {
            format_version: triax_protocol::JSON_FORMAT_VERSION,
            building: BuildingId::new(building).unwrap(),
            window_start_ns: start_ns,
            window_end_ns: start_ns + 10,
            sample_rate_hz: 100.0,
            identification_rate_hz: 0.0,
            sensors: Vec::new(),
            temperature_c: None,
            regressors: Vec::new(),
            tracked: false,
            modes: Vec::new(),
            unquantified: Vec::new(),
            refused: Some("test".into()),
            warnings: Vec::new(),
            late: false,
            identified_at: OffsetDateTime::UNIX_EPOCH,
        })
    }

    #[test]
    fn bounded_in_windows_and_buildings_and_watched_only_when_asked() {
        let mut book = ModesBook::default();
        for i in 0..(MAX_WINDOWS as i64 + 5) {
            book.on_message("triax/a/modes", &window("a", i * 10));
        }
        let v = book.view(&BuildingId::new("a").unwrap());
        assert_eq!(v["windows"], MAX_WINDOWS);
        assert_eq!(v["first_start_ns"], 50, "the oldest go first");
        for b in 0..crate::fleet::MAX_BUILDINGS + 3 {
            let id = format!("b{b}");
            book.on_message(&format!("triax/{id}/modes"), &window(&id, 0));
        }
        assert_eq!(book.buildings().len(), crate::fleet::MAX_BUILDINGS);
        assert_eq!(book.dropped, 4, "a is one of the thousand");
        book.on_message("triax/a/modes", b"not json");
        book.on_message("triax/a/modes", &window("b", 0));
        assert_eq!(book.malformed, 2);

        let mut watched = ModesBook::new(vec![BuildingId::new("hq").unwrap()]);
        watched.on_message("triax/other/modes", &window("other", 0));
        watched.on_message("triax/hq/modes", &window("hq", 0));
        assert_eq!(watched.buildings(), vec![BuildingId::new("hq").unwrap()]);
    }
}
