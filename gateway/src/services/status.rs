//! The status queryable's answer: gateway counters and, a page at a time, the sensors.
//!
//! A gateway may track up to `max_sensors` (100 000 by default) sensors, about 300 bytes of JSON
//! each, while a status reply must stay under the JSON limit of 8 MiB. So a reply lists at most
//! [`STATUS_PAGE_MAX`] sensors, sorted by id, and says where the next page starts. The
//! selector's parameters choose what to list:
//!
//! - `sensor=<id>`: that sensor only;
//! - `offset=<n>`: the page starting at the n-th sensor (default 0);
//! - `limit=<n>`: at most n sensors (default and cap [`STATUS_PAGE_MAX`]; 0 lists none, for
//!   the counters alone).
//!
//! Anything else is refused with a reply error that names the parameter.
//!
//! A one-sensor answer also carries the calibration record in force, read from the store: the
//! certificate an operator's console shows. The status path may therefore touch the store, and
//! runs on a blocking thread; the sample path never does.

use std::sync::atomic::Ordering::Relaxed;
use std::sync::Arc;

use time::OffsetDateTime;
use triax_calibration_store::Store;
use triax_protocol::keys::RawKeyRefusal;
use triax_protocol::messages::GatewayStatus;
use triax_protocol::provenance::check_nonce;
use triax_protocol::record::CalibrationRecord;
use triax_protocol::{to_json, Key, SensorId, JSON_FORMAT_VERSION};

use super::{Context, Task};
use crate::config::Config;
use crate::error::{zenoh_err, GatewayError};
use crate::sample_path::Sink;
use crate::shutdown::Shutdown;
use crate::state::{BackfillCounters, GatewayCounters, SensorTable, Signer};

/// Most sensors in one status reply: about 1.5 MiB of JSON.
pub const STATUS_PAGE_MAX: usize = 5000;

/// What a status query asks for.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct StatusQuery {
    pub sensor: Option<SensorId>,
    pub offset: usize,
    pub limit: usize,
    /// What the reply's signature is bound to (PROTOCOL.md §6); empty when not asked.
    pub nonce: String,
}

impl Default for StatusQuery {
    fn default() -> Self {
        StatusQuery {
            sensor: None,
            offset: 0,
            limit: STATUS_PAGE_MAX,
            nonce: String::new(),
        }
    }
}

impl StatusQuery {
    /// Reads the selector's parameters; the error names the parameter and what is wrong.
    pub fn parse<'a>(
        parameters: impl IntoIterator<Item = (&'a str, &'a str)>,
    ) -> Result<StatusQuery, String> {
        let mut q = StatusQuery::default();
        let number = |name: &str, value: &str| {
            value
                .parse::<usize>()
                .map_err(|_| format!("status query: {name}: {value:?} is not a whole number"))
        };
        for (name, value) in parameters {
            match name {
                "sensor" => {
                    q.sensor = Some(
                        SensorId::new(value).map_err(|e| format!("status query: sensor: {e}"))?,
                    )
                }
                "offset" => q.offset = number(name, value)?,
                "limit" => q.limit = number(name, value)?.min(STATUS_PAGE_MAX),
                "nonce" => {
                    check_nonce(value).map_err(|e| format!("status query: {e}"))?;
                    q.nonce = value.to_owned();
                }
                other => {
                    return Err(format!(
                        "status query: unknown parameter {other:?} (known: sensor, offset, limit, nonce)"
                    ))
                }
            }
        }
        Ok(q)
    }
}

/// What the status queryable reads.
pub struct StatusContext {
    pub config: Arc<Config>,
    pub table: Arc<SensorTable>,
    pub counters: Arc<GatewayCounters>,
    pub history: Option<Arc<Sink>>,
    pub backfill: Option<Arc<BackfillCounters>>,
    pub started_at: OffsetDateTime,
    /// Where a one-sensor answer reads the record in force; none: answers carry no record.
    pub store: Option<Arc<Store>>,
    pub signer: Arc<Signer>,
}

impl StatusContext {
    /// The answer to `query`. May read the store (a one-sensor query): call it from a blocking
    /// thread.
    pub fn status(&self, query: &StatusQuery) -> GatewayStatus {
        let c = &self.counters;
        let (total, sensors, next_offset) = match &query.sensor {
            // One lookup: no need to list and sort every sensor.
            Some(id) => (
                self.table.len(),
                self.table
                    .get(id)
                    .iter()
                    .map(|e| {
                        let mut s = e.status();
                        s.calibration_record = self.record(id, s.calibration_version);
                        s
                    })
                    .collect(),
                None,
            ),
            None => {
                let all = self.table.snapshot();
                let total = all.len();
                let end = query.offset.saturating_add(query.limit).min(total);
                let page = all.get(query.offset..end).unwrap_or_default();
                let next = (end < total && query.limit > 0).then_some(end as u64);
                (total, page.iter().map(|e| e.status()).collect(), next)
            }
        };
        GatewayStatus {
            format_version: JSON_FORMAT_VERSION,
            building: self.config.building.clone(),
            gateway: self.config.gateway_name.clone(),
            started_at: self.started_at,
            reported_at: OffsetDateTime::now_utc(),
            malformed: c.malformed.load(Relaxed),
            dropped: c.dropped.load(Relaxed),
            pushes_accepted: c.pushes_accepted.load(Relaxed),
            pushes_refused: c.pushes_refused.load(Relaxed),
            refused_keys: RawKeyRefusal::ALL
                .iter()
                .map(|&r| (r.as_str().to_owned(), c.refused_keys(r)))
                .collect(),
            over_capacity: c.over_capacity.load(Relaxed),
            admitted_sensors: self.table.admission.admitted.load(Relaxed),
            displaced_sensors: self.table.admission.displaced.load(Relaxed),
            expired_sensors: self.table.admission.expired.load(Relaxed),
            history: self.history.as_ref().map(|h| h.status()),
            backfill: self.backfill.as_ref().map(|b| b.status()),
            total_sensors: total as u64,
            next_offset,
            sensors,
        }
    }

    /// The stored record of `version` (the one in force); none if there is no store, no
    /// version, or the entry cannot be read (logged: the answer still carries the counters).
    fn record(&self, id: &SensorId, version: Option<u64>) -> Option<Box<CalibrationRecord>> {
        let (store, version) = (self.store.as_ref()?, version?);
        match store.get(id, version) {
            Ok(r) => r.map(Box::new),
            Err(e) => {
                tracing::warn!(sensor = %id, version, cause = %e, "status: record in force unreadable");
                None
            }
        }
    }
}

/// Starts the status queryable.
pub async fn start(
    ctx: &Context,
    history: Option<&Arc<Sink>>,
    backfill: Option<Arc<BackfillCounters>>,
) -> Result<Task, GatewayError> {
    let status = StatusContext {
        config: ctx.config.clone(),
        table: ctx.table.clone(),
        counters: ctx.counters.clone(),
        history: history.cloned(),
        backfill,
        started_at: ctx.started_at,
        store: Some(ctx.store.clone()),
        signer: ctx.signer.clone(),
    };
    serve(&ctx.session, status, ctx.shutdown.clone()).await
}

/// Answers status queries until shutdown.
async fn serve(
    session: &zenoh::Session,
    ctx: StatusContext,
    mut shutdown: Shutdown,
) -> Result<Task, GatewayError> {
    let queryable = session
        .declare_queryable(Key::Status(ctx.config.building.clone()).to_string())
        .await
        .map_err(zenoh_err("declare the status queryable"))?;
    let ctx = Arc::new(ctx);
    Ok(tokio::spawn(async move {
        loop {
            let query = tokio::select! {
                q = queryable.recv_async() => match q { Ok(q) => q, Err(_) => break },
                _ = shutdown.recv() => break,
            };
            let replied = match StatusQuery::parse(query.parameters().iter()) {
                Ok(q) => {
                    // A one-sensor answer reads the store.
                    let c = ctx.clone();
                    let nonce = q.nonce.clone();
                    let Ok(body) =
                        tokio::task::spawn_blocking(move || to_json(&c.status(&q))).await
                    else {
                        tracing::error!("status answer panicked");
                        continue;
                    };
                    let key = Key::Status(ctx.config.building.clone()).to_string();
                    let signature = ctx.signer.attachment(&key, &nonce, &body);
                    let reply = query.reply(key, body).attachment(signature);
                    reply.await
                }
                Err(problem) => query.reply_err(problem).await,
            };
            if let Err(e) = replied {
                tracing::warn!(cause = %e, "status reply failed");
            }
        }
    }))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn context(n: usize) -> StatusContext {
        let config = Arc::new(Config::for_tests(
            "st",
            std::path::Path::new("/nonexistent"),
            vec![],
        ));
        let table = Arc::new(SensorTable::new(config.clone()));
        for i in 0..n {
            table.entry(&SensorId::new(format!("s{i:03}")).unwrap());
        }
        StatusContext {
            config,
            table,
            counters: Arc::default(),
            history: None,
            backfill: None,
            started_at: OffsetDateTime::UNIX_EPOCH,
            store: None,
            signer: Arc::new(Signer::off()),
        }
    }

    fn ids(s: &GatewayStatus) -> Vec<&str> {
        s.sensors.iter().map(|s| s.sensor_id.as_str()).collect()
    }

    #[test]
    fn pages_walk_every_sensor_once_in_id_order() {
        let ctx = context(7);
        let mut q = StatusQuery::parse([("limit", "3")]).unwrap();
        let mut seen = Vec::new();
        loop {
            let s = ctx.status(&q);
            assert_eq!(s.total_sensors, 7);
            seen.extend(ids(&s).into_iter().map(String::from));
            match s.next_offset {
                Some(next) => q.offset = next as usize,
                None => break,
            }
        }
        let expected: Vec<String> = (0..7).map(|i| format!("s{i:03}")).collect();
        assert_eq!(seen, expected);
    }

    #[test]
    fn one_sensor_none_and_past_the_end() {
        let ctx = context(4);
        let s = ctx.status(&StatusQuery::parse([("sensor", "s002")]).unwrap());
        assert_eq!(
            (ids(&s), s.next_offset, s.total_sensors),
            (vec!["s002"], None, 4)
        );
        let s = ctx.status(&StatusQuery::parse([("sensor", "nope")]).unwrap());
        assert!(s.sensors.is_empty());
        let s = ctx.status(&StatusQuery::parse([("limit", "0")]).unwrap());
        assert!(
            s.sensors.is_empty() && s.next_offset.is_none(),
            "counters only"
        );
        let s = ctx.status(&StatusQuery::parse([("offset", "9")]).unwrap());
        assert!(s.sensors.is_empty() && s.next_offset.is_none());
        let s = ctx.status(&StatusQuery::default());
        assert_eq!(ids(&s).len(), 4);
        assert_eq!(s.next_offset, None);
    }

    #[test]
    fn limits_are_capped_and_bad_parameters_named() {
        let q = StatusQuery::parse([("limit", "999999")]).unwrap();
        assert_eq!(q.limit, STATUS_PAGE_MAX);
        let e = StatusQuery::parse([("limit", "ten")]).unwrap_err();
        assert!(e.contains("limit") && e.contains("\"ten\""), "{e}");
        let e = StatusQuery::parse([("page", "2")]).unwrap_err();
        assert!(e.contains("\"page\""), "{e}");
        let e = StatusQuery::parse([("sensor", "a/b")]).unwrap_err();
        assert!(e.contains("sensor"), "{e}");
    }
}
