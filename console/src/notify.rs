//! Notifications that leave the console: a webhook (an HTTP `POST` of JSON) or an e-mail (SMTP)
//! when a verified `exceeded` or `stale` alert arrives, or a sensor becomes
//! `calibration_suspect` or `silent`; per building a rota of shifts that says which channels are
//! told, quiet hours during which all but `exceeded` wait, escalation of an alert nobody
//! acknowledged, and one digest for a flood.
//!
//! The decisions are made by [`Dispatcher`], which does no I/O and takes the time as an
//! argument, so that shifts, quiet hours, digests and escalation are tested with a clock of the
//! test's own; [`start`] feeds it notices and the clock, and sends what it decides on each
//! channel's own task. Senders are small hand-written clients on tokio, as the console's server
//! is: HTTP/1.1 `POST` with a `Content-Length` to an `http://` URL, and SMTP (`EHLO`, `MAIL`,
//! `RCPT`, `DATA`, `QUIT`) to a relay, without TLS or authentication: the site's own relay (a
//! local MTA, a chat bridge) carries them further.
//!
//! Bounded: notices wait in a channel of [`QUEUE`] (beyond: counted as dropped), a digest lists
//! at most [`DIGEST_LISTED`] notices and counts the rest, held notices (quiet hours) at most
//! [`MAX_HELD`] a rota, escalations pending at most [`MAX_PENDING_ESCALATIONS`], the log of
//! what was sent [`LOG_KEPT`] entries.

use std::collections::{BTreeMap, HashMap, VecDeque};
use std::path::Path;
use std::sync::{Arc, Mutex};
use std::time::Duration;

use serde::{Deserialize, Serialize};
use tokio::io::{AsyncBufReadExt, AsyncReadExt, AsyncWriteExt, BufReader};
use tokio::net::TcpStream;
use triax_protocol::{BuildingId, SensorId};

use crate::SiteTimeZone;

/// Notices waiting for the dispatcher.
pub const QUEUE: usize = 10_000;
/// Notices listed in one digest (the rest counted).
pub const DIGEST_LISTED: usize = 50;
/// Notices held for the end of quiet hours, per rota.
pub const MAX_HELD: usize = 10_000;
/// Alerts waiting to be escalated.
pub const MAX_PENDING_ESCALATIONS: usize = 10_000;
/// Entries of the log of what was sent (`/api/notifications`).
pub const LOG_KEPT: usize = 200;
/// How long one delivery may take.
pub const SEND_TIMEOUT: Duration = Duration::from_secs(10);
/// Attempts per message (then it is logged as failed).
pub const ATTEMPTS: usize = 3;

/// What may be notified.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Event {
    /// A verified alert at level `exceeded`.
    Exceeded,
    /// A verified alert at level `stale` (the alerting service has no data to judge).
    Stale,
    /// The sensor's state became `calibration_suspect`.
    CalibrationSuspect,
    /// The sensor's state became `silent` (no batch for 10 s).
    Silent,
}

impl Event {
    pub const ALL: [Event; 4] = [
        Event::Exceeded,
        Event::Stale,
        Event::CalibrationSuspect,
        Event::Silent,
    ];

    pub fn name(self) -> &'static str {
        match self {
            Event::Exceeded => "exceeded",
            Event::Stale => "stale",
            Event::CalibrationSuspect => "calibration_suspect",
            Event::Silent => "silent",
        }
    }
}

/// Something that happened, as a notification tells it.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Notice {
    pub event: Event,
    pub building: BuildingId,
    pub sensor: SensorId,
    /// The alert's id in the console's log, for an alert.
    pub alert_id: Option<u64>,
    /// One line, made by the console from the alert's numbers or the sensor's state.
    pub summary: String,
    /// The alerting service's statement, as signed (free text: put in bodies only).
    #[serde(skip_serializing_if = "Option::is_none")]
    pub statement: Option<String>,
    /// When the console learnt of it, ns since the Unix epoch.
    pub at_ns: i64,
}

// ---- Settings ---------------------------------------------------------------------------------

/// The notification settings file (TOML), as written.
#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Settings {
    #[serde(default)]
    pub channels: BTreeMap<String, ChannelSettings>,
    #[serde(default)]
    pub rota: Vec<RotaSettings>,
    #[serde(default)]
    pub digest: DigestSettings,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ChannelSettings {
    /// `http://host:port/path`: a `POST` of JSON.
    pub webhook: Option<String>,
    /// `host:port` of an SMTP relay.
    pub smtp: Option<String>,
    /// The envelope and header sender of the e-mails.
    pub from: Option<String>,
    /// The e-mails' recipients.
    #[serde(default)]
    pub to: Vec<String>,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RotaSettings {
    /// A building id, or `*`: every building without a rota of its own.
    pub building: String,
    /// What is notified (default: every event).
    pub events: Option<Vec<Event>>,
    /// Who is told when, in the site's time zone; the first shift that holds the time wins.
    #[serde(default)]
    pub shift: Vec<ShiftSettings>,
    /// `HH:MM-HH:MM`: all but `exceeded` wait, and go as one digest when they end.
    pub quiet_hours: Option<String>,
    /// A verified alert notified and not acknowledged after this long goes to `escalate_to`.
    pub escalate_after_s: Option<f64>,
    #[serde(default)]
    pub escalate_to: Vec<String>,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ShiftSettings {
    /// `HH:MM`, inclusive.
    pub from: String,
    /// `HH:MM`, exclusive; before `from`: the shift runs past midnight.
    pub to: String,
    pub channels: Vec<String>,
}

#[derive(Debug, Clone, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DigestSettings {
    /// After a message on a channel, what follows within this many seconds waits and goes as
    /// one digest at its end.
    #[serde(default = "default_window_s")]
    pub window_s: f64,
}

fn default_window_s() -> f64 {
    60.0
}

impl Default for DigestSettings {
    fn default() -> Self {
        DigestSettings {
            window_s: default_window_s(),
        }
    }
}

/// A bad settings file: where and what.
#[derive(Debug, thiserror::Error)]
pub enum NotifyError {
    #[error("notification settings {path}: {source}")]
    Io {
        path: String,
        #[source]
        source: std::io::Error,
    },
    #[error("notification settings {path}: {message}")]
    Invalid { path: String, message: String },
}

/// A webhook's address.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct HttpUrl {
    pub host: String,
    pub port: u16,
    pub path: String,
}

impl HttpUrl {
    pub fn parse(url: &str) -> Result<HttpUrl, String> {
        let rest = url.strip_prefix("http://").ok_or_else(|| {
            format!("{url:?} is not an http:// URL (https goes through a local relay)")
        })?;
        let (authority, path) = match rest.find('/') {
            Some(i) => (&rest[..i], &rest[i..]),
            None => (rest, "/"),
        };
        let (host, port) = match authority.rsplit_once(':') {
            Some((h, p)) if !h.ends_with(']') || h.starts_with('[') => (
                h,
                p.parse::<u16>()
                    .map_err(|_| format!("{url:?}: port {p:?} is not a number"))?,
            ),
            _ => (authority, 80),
        };
        if host.is_empty() || host.contains(['@', ' ']) {
            return Err(format!("{url:?}: no host"));
        }
        if path.contains([' ', '\r', '\n']) {
            return Err(format!("{url:?}: the path has a space or a line break"));
        }
        Ok(HttpUrl {
            host: host.to_owned(),
            port,
            path: path.to_owned(),
        })
    }
}

/// A channel ready to send.
#[derive(Debug, Clone)]
pub enum Channel {
    Webhook(HttpUrl),
    Smtp {
        relay: String,
        from: String,
        to: Vec<String>,
    },
}

#[derive(Debug, Clone)]
struct Shift {
    from_min: u32,
    to_min: u32,
    channels: Vec<String>,
}

#[derive(Debug, Clone)]
struct Rota {
    building: Option<BuildingId>,
    events: Vec<Event>,
    shifts: Vec<Shift>,
    quiet: Option<(u32, u32)>,
    escalate_after_ns: Option<i64>,
    escalate_to: Vec<String>,
}

/// Settings checked: every channel a rota names exists, every time reads.
#[derive(Debug, Clone)]
pub struct Config {
    pub channels: BTreeMap<String, Channel>,
    rotas: Vec<Rota>,
    digest_window_ns: i64,
}

fn minutes(field: &str, text: &str) -> Result<u32, String> {
    let bad = || format!("{field}: {text:?} is not a time HH:MM");
    let (h, m) = text.split_once(':').ok_or_else(bad)?;
    let (h, m): (u32, u32) = (h.parse().map_err(|_| bad())?, m.parse().map_err(|_| bad())?);
    if h > 24 || m > 59 || (h == 24 && m > 0) {
        return Err(bad());
    }
    Ok(h * 60 + m)
}

/// Whether minute `t` of the day is within `[from, to)`, which may run past midnight.
fn within(t: u32, from: u32, to: u32) -> bool {
    if from <= to {
        from <= t && t < to
    } else {
        t >= from || t < to
    }
}

/// Whether to send an e-mail address as it is: no line breaks, brackets or spaces that could
/// change the SMTP command it goes into.
fn check_address(field: &str, a: &str) -> Result<(), String> {
    if a.is_empty()
        || a.len() > 254
        || !a.contains('@')
        || a.chars()
            .any(|c| c.is_control() || c.is_whitespace() || "<>\",;".contains(c))
    {
        return Err(format!("{field}: {a:?} is not an e-mail address"));
    }
    Ok(())
}

impl Config {
    /// Reads and checks a settings file.
    pub fn load(path: &Path) -> Result<Config, NotifyError> {
        let p = path.display().to_string();
        let text = std::fs::read_to_string(path).map_err(|source| NotifyError::Io {
            path: p.clone(),
            source,
        })?;
        let settings: Settings = toml::from_str(&text).map_err(|e| NotifyError::Invalid {
            path: p.clone(),
            message: e.to_string(),
        })?;
        Config::from_settings(settings).map_err(|message| NotifyError::Invalid { path: p, message })
    }

    pub fn from_settings(s: Settings) -> Result<Config, String> {
        let mut channels = BTreeMap::new();
        for (name, c) in &s.channels {
            let at = |f: &str| format!("channels.{name}.{f}");
            let ch = match (&c.webhook, &c.smtp) {
                (Some(url), None) => {
                    if c.from.is_some() || !c.to.is_empty() {
                        return Err(format!("channels.{name}: a webhook takes no from or to"));
                    }
                    Channel::Webhook(
                        HttpUrl::parse(url).map_err(|e| format!("{}: {e}", at("webhook")))?,
                    )
                }
                (None, Some(relay)) => {
                    if relay
                        .rsplit_once(':')
                        .is_none_or(|(_, p)| p.parse::<u16>().is_err())
                    {
                        return Err(format!("{}: {relay:?} is not host:port", at("smtp")));
                    }
                    let from = c
                        .from
                        .clone()
                        .ok_or_else(|| format!("{} is required for e-mail", at("from")))?;
                    check_address(&at("from"), &from)?;
                    if c.to.is_empty() {
                        return Err(format!("{} needs at least one address", at("to")));
                    }
                    for a in &c.to {
                        check_address(&at("to"), a)?;
                    }
                    Channel::Smtp {
                        relay: relay.clone(),
                        from,
                        to: c.to.clone(),
                    }
                }
                _ => {
                    return Err(format!(
                        "channels.{name}: give exactly one of webhook or smtp"
                    ))
                }
            };
            channels.insert(name.clone(), ch);
        }
        let known = |field: &str, names: &[String]| -> Result<(), String> {
            match names.iter().find(|n| !channels.contains_key(*n)) {
                Some(n) => Err(format!(
                    "{field}: no channel {n:?} (channels: {})",
                    channels.keys().cloned().collect::<Vec<_>>().join(", ")
                )),
                None => Ok(()),
            }
        };
        let mut rotas = Vec::new();
        for (i, r) in s.rota.iter().enumerate() {
            let at = |f: &str| format!("rota[{i}].{f}");
            let building = if r.building == "*" {
                None
            } else {
                Some(BuildingId::new(&r.building).map_err(|e| format!("{}: {e}", at("building")))?)
            };
            if rotas.iter().any(|x: &Rota| x.building == building) {
                return Err(format!(
                    "{}: {:?} has a rota already",
                    at("building"),
                    r.building
                ));
            }
            let mut shifts = Vec::new();
            for (j, sh) in r.shift.iter().enumerate() {
                let f = format!("rota[{i}].shift[{j}]");
                known(&format!("{f}.channels"), &sh.channels)?;
                shifts.push(Shift {
                    from_min: minutes(&format!("{f}.from"), &sh.from)?,
                    to_min: minutes(&format!("{f}.to"), &sh.to)?,
                    channels: sh.channels.clone(),
                });
            }
            if shifts.is_empty() {
                return Err(format!("{}: at least one shift", at("shift")));
            }
            let quiet = match &r.quiet_hours {
                None => None,
                Some(q) => {
                    let (a, b) = q.split_once('-').ok_or_else(|| {
                        format!("{}: {q:?} is not HH:MM-HH:MM", at("quiet_hours"))
                    })?;
                    Some((
                        minutes(&at("quiet_hours"), a)?,
                        minutes(&at("quiet_hours"), b)?,
                    ))
                }
            };
            known(&at("escalate_to"), &r.escalate_to)?;
            let escalate_after_ns = match r.escalate_after_s {
                None => None,
                Some(s) if s.is_finite() && s > 0.0 && s <= 7.0 * 86_400.0 => {
                    if r.escalate_to.is_empty() {
                        return Err(format!(
                            "{}: escalate_after_s needs escalate_to",
                            at("escalate_to")
                        ));
                    }
                    Some((s * 1e9) as i64)
                }
                Some(s) => {
                    return Err(format!(
                        "{}: {s} is not from 0 to 604800 s",
                        at("escalate_after_s")
                    ))
                }
            };
            rotas.push(Rota {
                building,
                events: r.events.clone().unwrap_or_else(|| Event::ALL.to_vec()),
                shifts,
                quiet,
                escalate_after_ns,
                escalate_to: r.escalate_to.clone(),
            });
        }
        let w = s.digest.window_s;
        if !(w.is_finite() && (0.0..=3600.0).contains(&w)) {
            return Err(format!("digest.window_s: {w} is not from 0 to 3600 s"));
        }
        Ok(Config {
            channels,
            rotas,
            digest_window_ns: (w * 1e9) as i64,
        })
    }

    fn rota_of(&self, b: &BuildingId) -> Option<usize> {
        self.rotas
            .iter()
            .position(|r| r.building.as_ref() == Some(b))
            .or_else(|| self.rotas.iter().position(|r| r.building.is_none()))
    }
}

// ---- Decisions --------------------------------------------------------------------------------

/// A message to send on one channel.
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct Message {
    pub channel: String,
    /// `notification` (one notice), `digest` (several, after a flood or quiet hours) or
    /// `escalation` (a notified alert nobody acknowledged).
    pub kind: &'static str,
    /// Notices listed (at most [`DIGEST_LISTED`]).
    pub notices: Vec<Notice>,
    /// Notices it stands for (beyond the listed ones too).
    pub count: usize,
    /// Why held, for a digest after quiet hours.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub reason: Option<&'static str>,
}

#[derive(Debug, Default)]
struct ChannelState {
    /// When the last message left, ns.
    last_sent_ns: Option<i64>,
    /// Waiting for the end of the digest window.
    pending: Vec<Notice>,
    pending_count: usize,
}

#[derive(Debug)]
struct Escalation {
    due_ns: i64,
    notice: Notice,
    to: Vec<String>,
}

/// The decisions: which notices go where and when. No I/O, no clock of its own.
pub struct Dispatcher {
    config: Config,
    zone: Option<SiteTimeZone>,
    channels: HashMap<String, ChannelState>,
    /// Per rota: notices held by quiet hours, and whether they were on at the last look.
    held: Vec<(Vec<Notice>, usize, bool)>,
    escalations: VecDeque<Escalation>,
    /// Notices not notified: no rota, an event the rota leaves out, or no shift then.
    pub unrouted: u64,
    /// Held or escalations over their bounds.
    pub dropped: u64,
}

impl Dispatcher {
    pub fn new(config: Config, zone: Option<SiteTimeZone>) -> Dispatcher {
        let held = config
            .rotas
            .iter()
            .map(|_| (Vec::new(), 0, false))
            .collect();
        Dispatcher {
            config,
            zone,
            channels: HashMap::new(),
            held,
            escalations: VecDeque::new(),
            unrouted: 0,
            dropped: 0,
        }
    }

    pub fn config(&self) -> &Config {
        &self.config
    }

    fn minute(&self, t_ns: i64) -> u32 {
        match &self.zone {
            Some(z) => z.minute_of_day(t_ns).0,
            None => (t_ns.div_euclid(60_000_000_000).rem_euclid(24 * 60)) as u32,
        }
    }

    fn quiet(&self, rota: &Rota, t_ns: i64) -> bool {
        rota.quiet
            .is_some_and(|(a, b)| within(self.minute(t_ns), a, b))
    }

    fn shift_channels(&self, rota: &Rota, t_ns: i64) -> Vec<String> {
        let m = self.minute(t_ns);
        rota.shifts
            .iter()
            .find(|s| within(m, s.from_min, s.to_min))
            .map(|s| s.channels.clone())
            .unwrap_or_default()
    }

    /// A notice arrives at `now_ns`: what to send now.
    pub fn notice(&mut self, n: Notice, now_ns: i64) -> Vec<Message> {
        let Some(ri) = self.config.rota_of(&n.building) else {
            self.unrouted += 1;
            return Vec::new();
        };
        let rota = self.config.rotas[ri].clone();
        if !rota.events.contains(&n.event) {
            self.unrouted += 1;
            return Vec::new();
        }
        if n.event != Event::Exceeded && self.quiet(&rota, now_ns) {
            let held = &mut self.held[ri];
            held.1 += 1;
            if held.0.len() < MAX_HELD {
                held.0.push(n);
            } else {
                self.dropped += 1;
            }
            return Vec::new();
        }
        let channels = self.shift_channels(&rota, now_ns);
        if channels.is_empty() {
            self.unrouted += 1;
            return Vec::new();
        }
        if let (Some(after), Some(_)) = (rota.escalate_after_ns, n.alert_id) {
            if self.escalations.len() < MAX_PENDING_ESCALATIONS {
                self.escalations.push_back(Escalation {
                    due_ns: now_ns + after,
                    notice: n.clone(),
                    to: rota.escalate_to.clone(),
                });
            } else {
                self.dropped += 1;
            }
        }
        let mut out = Vec::new();
        for c in channels {
            out.extend(self.offer(&c, n.clone(), now_ns));
        }
        out
    }

    /// One notice for channel `c`: at once if the channel is free, else into its digest.
    fn offer(&mut self, c: &str, n: Notice, now_ns: i64) -> Option<Message> {
        let window = self.config.digest_window_ns;
        let st = self.channels.entry(c.to_owned()).or_default();
        let free = st.pending_count == 0 && st.last_sent_ns.is_none_or(|t| now_ns - t >= window);
        if free {
            st.last_sent_ns = Some(now_ns);
            return Some(Message {
                channel: c.to_owned(),
                kind: "notification",
                count: 1,
                notices: vec![n],
                reason: None,
            });
        }
        st.pending_count += 1;
        if st.pending.len() < DIGEST_LISTED {
            st.pending.push(n);
        }
        None
    }

    /// The clock moves to `now_ns`: digests whose window ended, quiet hours that ended,
    /// escalations due for alerts `acknowledged` does not know as acknowledged.
    pub fn tick(&mut self, now_ns: i64, acknowledged: &dyn Fn(u64) -> bool) -> Vec<Message> {
        let mut out = Vec::new();
        // Quiet hours that ended: what they held, as one digest per channel of the shift.
        for ri in 0..self.config.rotas.len() {
            let rota = self.config.rotas[ri].clone();
            let quiet = self.quiet(&rota, now_ns);
            let was = self.held[ri].2;
            self.held[ri].2 = quiet;
            if was && !quiet && self.held[ri].1 > 0 {
                let (list, count) = (std::mem::take(&mut self.held[ri].0), self.held[ri].1);
                self.held[ri].1 = 0;
                for c in self.shift_channels(&rota, now_ns) {
                    let st = self.channels.entry(c.clone()).or_default();
                    st.last_sent_ns = Some(now_ns);
                    out.push(Message {
                        channel: c,
                        kind: "digest",
                        notices: list.iter().take(DIGEST_LISTED).cloned().collect(),
                        count,
                        reason: Some("quiet hours ended"),
                    });
                }
            }
        }
        // Escalations due.
        while self.escalations.front().is_some_and(|e| e.due_ns <= now_ns) {
            let Some(e) = self.escalations.pop_front() else {
                break;
            };
            if e.notice.alert_id.is_some_and(acknowledged) {
                continue;
            }
            for c in e.to {
                // An escalation is never folded into a digest: it is the one that must be read.
                self.channels.entry(c.clone()).or_default().last_sent_ns = Some(now_ns);
                out.push(Message {
                    channel: c,
                    kind: "escalation",
                    notices: vec![e.notice.clone()],
                    count: 1,
                    reason: None,
                });
            }
        }
        // Digests whose window ended.
        let window = self.config.digest_window_ns;
        for (c, st) in &mut self.channels {
            if st.pending_count > 0 && st.last_sent_ns.is_none_or(|t| now_ns - t >= window) {
                out.push(Message {
                    channel: c.clone(),
                    kind: "digest",
                    notices: std::mem::take(&mut st.pending),
                    count: std::mem::take(&mut st.pending_count),
                    reason: None,
                });
                st.last_sent_ns = Some(now_ns);
            }
        }
        out
    }

    /// Notices held by quiet hours now, per rota.
    pub fn held(&self) -> usize {
        self.held.iter().map(|h| h.1).sum()
    }
}

// ---- Messages as they are sent ------------------------------------------------------------------

/// The JSON a webhook receives.
pub fn webhook_body(m: &Message) -> String {
    serde_json::to_string(&serde_json::json!({
        "source": "triax-console",
        "kind": m.kind,
        "count": m.count,
        "reason": m.reason,
        "notices": m.notices,
    }))
    .unwrap_or_default()
}

/// ASCII letters, digits and a few signs: what a header may carry from a notice.
fn header_safe(s: &str) -> String {
    s.chars()
        .map(|c| {
            if c.is_ascii_graphic() || c == ' ' {
                c
            } else {
                '?'
            }
        })
        .collect()
}

/// The subject line of an e-mail.
pub fn subject(m: &Message) -> String {
    let s = match (m.kind, m.notices.first()) {
        ("digest", _) => format!("[triax] digest: {} notifications", m.count),
        (kind, Some(n)) => format!(
            "[triax] {}{}/{} {}",
            if kind == "escalation" {
                "UNACKNOWLEDGED: "
            } else {
                ""
            },
            n.building,
            n.sensor,
            n.event.name()
        ),
        (_, None) => "[triax] notification".to_owned(),
    };
    header_safe(&s)
}

/// The text of an e-mail: one paragraph per notice, the statement as signed.
pub fn mail_text(m: &Message) -> String {
    let mut t = String::new();
    match m.kind {
        "digest" => t.push_str(&format!(
            "{} notifications{}; {} listed.\n\n",
            m.count,
            m.reason.map(|r| format!(" ({r})")).unwrap_or_default(),
            m.notices.len()
        )),
        "escalation" => t.push_str("Nobody has acknowledged this alert yet.\n\n"),
        _ => {}
    }
    for n in &m.notices {
        let at = time::OffsetDateTime::from_unix_timestamp_nanos(i128::from(n.at_ns))
            .ok()
            .and_then(|d| {
                d.format(&time::format_description::well_known::Rfc3339)
                    .ok()
            })
            .unwrap_or_default();
        t.push_str(&format!(
            "{}/{}: {} ({at})\n{}\n",
            n.building,
            n.sensor,
            n.event.name(),
            n.summary
        ));
        if let Some(id) = n.alert_id {
            t.push_str(&format!("alert {id} in the console's log\n"));
        }
        if let Some(s) = &n.statement {
            t.push_str(s);
            t.push('\n');
        }
        t.push('\n');
    }
    t
}

/// Posts `body` to `url`; Ok with the status line's code if 2xx.
pub async fn post_webhook(url: &HttpUrl, body: &str) -> Result<u16, String> {
    let mut s = TcpStream::connect((url.host.as_str(), url.port))
        .await
        .map_err(|e| format!("connecting to {}:{}: {e}", url.host, url.port))?;
    let host = if url.port == 80 {
        url.host.clone()
    } else {
        format!("{}:{}", url.host, url.port)
    };
    let head = format!(
        "POST {} HTTP/1.1\r\nHost: {host}\r\nUser-Agent: triax-console\r\nContent-Type: application/json\r\nContent-Length: {}\r\nConnection: close\r\n\r\n",
        url.path,
        body.len()
    );
    s.write_all(head.as_bytes())
        .await
        .map_err(|e| e.to_string())?;
    s.write_all(body.as_bytes())
        .await
        .map_err(|e| e.to_string())?;
    let mut line = String::new();
    let mut r = BufReader::new(s.take(8192));
    r.read_line(&mut line)
        .await
        .map_err(|e| format!("reading the answer: {e}"))?;
    let code: u16 = line
        .split(' ')
        .nth(1)
        .and_then(|c| c.parse().ok())
        .ok_or_else(|| format!("not an HTTP answer: {:?}", line.trim_end()))?;
    if (200..300).contains(&code) {
        Ok(code)
    } else {
        Err(format!("answered {}", line.trim_end()))
    }
}

/// Sends one e-mail through an SMTP relay.
pub async fn send_mail(
    relay: &str,
    from: &str,
    to: &[String],
    subject: &str,
    text: &str,
) -> Result<(), String> {
    let s = TcpStream::connect(relay)
        .await
        .map_err(|e| format!("connecting to {relay}: {e}"))?;
    let (rd, mut wr) = s.into_split();
    let mut rd = BufReader::new(rd.take(1 << 20));
    // A reply: lines `NNN-…` then `NNN …`; its code must start with `want`.
    async fn reply(
        rd: &mut BufReader<tokio::io::Take<tokio::net::tcp::OwnedReadHalf>>,
        want: char,
        after: &str,
    ) -> Result<(), String> {
        loop {
            let mut line = String::new();
            if rd.read_line(&mut line).await.map_err(|e| e.to_string())? == 0 {
                return Err(format!("the relay closed after {after}"));
            }
            if line.len() < 4 {
                return Err(format!("after {after}: {:?}", line.trim_end()));
            }
            if line.as_bytes()[3] == b'-' {
                continue;
            }
            if !line.starts_with(want) {
                return Err(format!("after {after}: {}", line.trim_end()));
            }
            return Ok(());
        }
    }
    async fn say(wr: &mut tokio::net::tcp::OwnedWriteHalf, line: &str) -> Result<(), String> {
        wr.write_all(line.as_bytes())
            .await
            .map_err(|e| e.to_string())
    }
    reply(&mut rd, '2', "connecting").await?;
    say(&mut wr, "EHLO triax-console\r\n").await?;
    reply(&mut rd, '2', "EHLO").await?;
    say(&mut wr, &format!("MAIL FROM:<{from}>\r\n")).await?;
    reply(&mut rd, '2', "MAIL FROM").await?;
    for t in to {
        say(&mut wr, &format!("RCPT TO:<{t}>\r\n")).await?;
        reply(&mut rd, '2', "RCPT TO").await?;
    }
    say(&mut wr, "DATA\r\n").await?;
    reply(&mut rd, '3', "DATA").await?;
    let date = time::OffsetDateTime::now_utc()
        .format(&time::format_description::well_known::Rfc2822)
        .unwrap_or_default();
    let mut msg = format!(
        "From: {from}\r\nTo: {}\r\nSubject: {subject}\r\nDate: {date}\r\nMIME-Version: 1.0\r\nContent-Type: text/plain; charset=utf-8\r\nContent-Transfer-Encoding: 8bit\r\n\r\n",
        to.join(", ")
    );
    // Every line break CRLF; a line that starts with a dot gets another (RFC 5321 §4.5.2), so
    // that a statement cannot end the message early.
    for line in text.split('\n') {
        let line = line.trim_end_matches('\r');
        if line.starts_with('.') {
            msg.push('.');
        }
        msg.push_str(line);
        msg.push_str("\r\n");
    }
    msg.push_str(".\r\n");
    say(&mut wr, &msg).await?;
    reply(&mut rd, '2', "the message").await?;
    let _ = say(&mut wr, "QUIT\r\n").await;
    Ok(())
}

// ---- The running side -----------------------------------------------------------------------------

/// One message as sent (or not), for `/api/notifications`.
#[derive(Debug, Clone, Serialize)]
pub struct Sent {
    #[serde(flatten)]
    pub message: Message,
    /// When it left (or was given up), ns.
    pub at_ns: i64,
    pub attempts: usize,
    pub error: Option<String>,
}

/// What `/api/notifications` shows.
#[derive(Debug, Default, Serialize)]
pub struct Status {
    pub configured: bool,
    pub channels: Vec<String>,
    pub sent: u64,
    pub failed: u64,
    /// Notices lost because the queue was full.
    pub dropped: u64,
    pub unrouted: u64,
    pub held: usize,
    /// The latest messages, newest first.
    pub recent: VecDeque<Sent>,
}

/// The console's side of the notifications: where notices are put, and what was sent.
#[derive(Clone)]
pub struct Notifier {
    tx: Option<tokio::sync::mpsc::Sender<Notice>>,
    pub status: Arc<Mutex<Status>>,
}

impl Notifier {
    /// No notifications configured: notices go nowhere.
    pub fn off() -> Notifier {
        Notifier {
            tx: None,
            status: Arc::new(Mutex::new(Status::default())),
        }
    }

    /// Puts a notice in the queue; never waits (a full queue counts it as dropped).
    pub fn put(&self, n: Notice) {
        let Some(tx) = &self.tx else { return };
        if tx.try_send(n).is_err() {
            self.status
                .lock()
                .unwrap_or_else(|p| p.into_inner())
                .dropped += 1;
        }
    }

    pub fn is_on(&self) -> bool {
        self.tx.is_some()
    }

    pub fn view(&self) -> serde_json::Value {
        serde_json::to_value(&*self.status.lock().unwrap_or_else(|p| p.into_inner()))
            .unwrap_or_default()
    }
}

/// Starts the dispatcher: returns the notifier to put notices in, and the task, which runs
/// until `stop` fires. `acknowledged` says whether an alert id is acknowledged.
pub fn start(
    config: Config,
    zone: Option<SiteTimeZone>,
    acknowledged: Arc<dyn Fn(u64) -> bool + Send + Sync>,
    mut stop: tokio::sync::watch::Receiver<bool>,
) -> (Notifier, tokio::task::JoinHandle<()>) {
    let (tx, mut rx) = tokio::sync::mpsc::channel::<Notice>(QUEUE);
    let status = Arc::new(Mutex::new(Status {
        configured: true,
        channels: config.channels.keys().cloned().collect(),
        ..Status::default()
    }));
    let notifier = Notifier {
        tx: Some(tx),
        status: status.clone(),
    };
    // One sender task per channel, so that a slow relay delays only its own messages.
    let mut senders: HashMap<String, tokio::sync::mpsc::Sender<Message>> = HashMap::new();
    for (name, ch) in &config.channels {
        let (mtx, mut mrx) = tokio::sync::mpsc::channel::<Message>(1000);
        let (ch, status) = (ch.clone(), status.clone());
        tokio::spawn(async move {
            while let Some(m) = mrx.recv().await {
                let mut error = None;
                let mut attempts = 0;
                for attempt in 0..ATTEMPTS {
                    attempts = attempt + 1;
                    let sent = match &ch {
                        Channel::Webhook(url) => {
                            tokio::time::timeout(SEND_TIMEOUT, post_webhook(url, &webhook_body(&m)))
                                .await
                                .map_err(|_| "timed out".to_owned())
                                .and_then(|r| r.map(|_| ()))
                        }
                        Channel::Smtp { relay, from, to } => tokio::time::timeout(
                            SEND_TIMEOUT,
                            send_mail(relay, from, to, &subject(&m), &mail_text(&m)),
                        )
                        .await
                        .map_err(|_| "timed out".to_owned())
                        .and_then(|r| r),
                    };
                    match sent {
                        Ok(()) => {
                            error = None;
                            break;
                        }
                        Err(e) => {
                            tracing::warn!(channel = %m.channel, cause = %e, attempt = attempts, "notification not sent");
                            error = Some(e);
                            tokio::time::sleep(Duration::from_secs(2 * (attempt as u64 + 1))).await;
                        }
                    }
                }
                let mut st = status.lock().unwrap_or_else(|p| p.into_inner());
                if error.is_some() {
                    st.failed += 1;
                } else {
                    st.sent += 1;
                }
                st.recent.push_front(Sent {
                    message: m,
                    at_ns: crate::live::wall_clock_ns(),
                    attempts,
                    error,
                });
                st.recent.truncate(LOG_KEPT);
            }
        });
        senders.insert(name.clone(), mtx);
    }
    let task = tokio::spawn(async move {
        let mut d = Dispatcher::new(config, zone);
        let mut tick = tokio::time::interval(Duration::from_millis(250));
        tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
        loop {
            let out = tokio::select! {
                _ = stop.changed() => return,
                n = rx.recv() => match n {
                    Some(n) => d.notice(n, crate::live::wall_clock_ns()),
                    None => return,
                },
                _ = tick.tick() => d.tick(crate::live::wall_clock_ns(), &*acknowledged),
            };
            {
                let mut st = status.lock().unwrap_or_else(|p| p.into_inner());
                st.unrouted = d.unrouted;
                st.held = d.held();
                st.dropped = st.dropped.max(d.dropped);
            }
            for m in out {
                if let Some(s) = senders.get(&m.channel) {
                    if s.try_send(m).is_err() {
                        status.lock().unwrap_or_else(|p| p.into_inner()).failed += 1;
                    }
                }
            }
        }
    });
    (notifier, task)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn config(toml_text: &str) -> Config {
        Config::from_settings(toml::from_str(toml_text).unwrap()).unwrap()
    }

    fn notice(event: Event, sensor: &str, id: Option<u64>) -> Notice {
        Notice {
            event,
            building: BuildingId::new("hq").unwrap(),
            sensor: SensorId::new(sensor).unwrap(),
            alert_id: id,
            summary: "s".into(),
            statement: None,
            at_ns: 0,
        }
    }

    const H: i64 = 3_600_000_000_000;
    const S: i64 = 1_000_000_000;
    /// 2027-01-04 00:00 UTC, a Monday.
    const DAY0: i64 = 1_799_020_800 * S;

    const SETTINGS: &str = r#"
        [channels.day]
        webhook = "http://127.0.0.1:9/day"
        [channels.night]
        smtp = "127.0.0.1:25"
        from = "triax@site.example"
        to = ["oncall@site.example"]
        [channels.boss]
        webhook = "http://127.0.0.1:9/boss"
        [[rota]]
        building = "hq"
        quiet_hours = "22:00-06:00"
        escalate_after_s = 600
        escalate_to = ["boss"]
        [[rota.shift]]
        from = "07:00"
        to = "19:00"
        channels = ["day"]
        [[rota.shift]]
        from = "19:00"
        to = "07:00"
        channels = ["night"]
        [digest]
        window_s = 60
    "#;

    #[test]
    fn shifts_choose_the_channels_and_a_flood_is_one_digest() {
        let mut d = Dispatcher::new(config(SETTINGS), None);
        let t = DAY0 + 10 * H;
        let out = d.notice(notice(Event::Exceeded, "a", Some(1)), t);
        assert_eq!(out.len(), 1);
        assert_eq!(
            (out[0].channel.as_str(), out[0].kind),
            ("day", "notification")
        );
        // 999 more within the window: none at once, one digest at its end.
        for i in 0..999 {
            assert!(d
                .notice(notice(Event::Exceeded, "a", Some(2 + i)), t + S)
                .is_empty());
        }
        assert!(d.tick(t + 59 * S, &|_| true).is_empty());
        let out = d.tick(t + 60 * S, &|_| true);
        assert_eq!(out.len(), 1, "{out:?}");
        assert_eq!(
            (out[0].kind, out[0].count, out[0].notices.len()),
            ("digest", 999, DIGEST_LISTED)
        );
        // At night, the night's channel.
        let out = d.notice(notice(Event::Exceeded, "a", Some(5000)), DAY0 + 20 * H);
        assert_eq!(out[0].channel, "night");
    }

    #[test]
    fn quiet_hours_hold_all_but_exceeded_until_they_end() {
        let mut d = Dispatcher::new(config(SETTINGS), None);
        let t = DAY0 + 23 * H;
        assert!(d.tick(t, &|_| true).is_empty());
        assert!(d.notice(notice(Event::Silent, "a", None), t).is_empty());
        assert!(d
            .notice(notice(Event::CalibrationSuspect, "b", None), t + S)
            .is_empty());
        assert_eq!(d.held(), 2);
        let out = d.notice(notice(Event::Exceeded, "c", Some(9)), t + 2 * S);
        assert_eq!(out[0].channel, "night", "exceeded is never held");
        assert!(d
            .tick(DAY0 + 24 * H + 5 * H + 59 * 60 * S, &|_| true)
            .is_empty());
        let out = d.tick(DAY0 + 24 * H + 6 * H, &|_| true);
        let held: Vec<_> = out.iter().filter(|m| m.reason.is_some()).collect();
        assert_eq!(held.len(), 1, "{out:?}");
        assert_eq!((held[0].count, held[0].channel.as_str()), (2, "night"));
        assert_eq!(d.held(), 0);
    }

    #[test]
    fn an_unacknowledged_alert_escalates_once() {
        let mut d = Dispatcher::new(config(SETTINGS), None);
        let t = DAY0 + 10 * H;
        d.notice(notice(Event::Exceeded, "a", Some(1)), t);
        d.notice(notice(Event::Exceeded, "b", Some(2)), t + S);
        let acked = |id: u64| id == 2;
        assert!(d
            .tick(t + 599 * S, &acked)
            .iter()
            .all(|m| m.kind != "escalation"));
        let out = d.tick(t + 601 * S, &acked);
        let esc: Vec<_> = out.iter().filter(|m| m.kind == "escalation").collect();
        assert_eq!(esc.len(), 1, "{out:?}");
        assert_eq!(
            (esc[0].channel.as_str(), esc[0].notices[0].alert_id),
            ("boss", Some(1))
        );
        assert!(d
            .tick(t + 2000 * S, &acked)
            .iter()
            .all(|m| m.kind != "escalation"));
    }

    #[test]
    fn settings_are_checked_and_named() {
        for (text, says) in [
            ("[[rota]]\nbuilding = \"hq\"\n[[rota.shift]]\nfrom = \"07:00\"\nto = \"19:00\"\nchannels = [\"x\"]", "no channel \"x\""),
            ("[channels.a]\nwebhook = \"https://x/\"", "not an http:// URL"),
            ("[channels.a]\nsmtp = \"relay:25\"\nto = [\"a@b\"]", "from is required"),
            ("[channels.a]\nsmtp = \"relay:25\"\nfrom = \"a@b\"\nto = [\"x\\r\\nRCPT TO:<e@f>\"]", "not an e-mail address"),
            ("[channels.a]\nwebhook = \"http://h/\"\n[[rota]]\nbuilding = \"hq\"\n[[rota.shift]]\nfrom = \"25:00\"\nto = \"19:00\"\nchannels = [\"a\"]", "rota[0].shift[0].from"),
            ("[digest]\nwindow_s = -1", "digest.window_s"),
        ] {
            let e = Config::from_settings(toml::from_str(text).unwrap())
                .map(|_| ())
                .unwrap_err();
            assert!(e.contains(says), "{text}: {e}");
        }
        assert!(toml::from_str::<Settings>("colour = 1").is_err());
        let u = HttpUrl::parse("http://127.0.0.1:8080/hook?x=1").unwrap();
        assert_eq!(
            (u.host.as_str(), u.port, u.path.as_str()),
            ("127.0.0.1", 8080, "/hook?x=1")
        );
    }

    #[test]
    fn a_statement_cannot_end_the_mail_or_reach_a_header() {
        let mut n = notice(Event::Exceeded, "a", Some(1));
        n.statement = Some("line\n.\nQUIT".into());
        let m = Message {
            channel: "c".into(),
            kind: "notification",
            notices: vec![n],
            count: 1,
            reason: None,
        };
        assert_eq!(subject(&m), "[triax] hq/a exceeded");
        assert!(
            mail_text(&m).contains("\n.\nQUIT"),
            "the text as written; dots are doubled on the wire"
        );
        assert_eq!(header_safe("a\r\nBcc: x"), "a??Bcc: x");
    }
}
