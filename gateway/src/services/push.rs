//! Calibration updates from the lab: a signed record is verified, validated, made durable and
//! only then put in force, and the sender gets a [`PushAck`].
//!
//! Two paths lead here and share [`Updater::apply`]: pushes, which the lab sends as Zenoh
//! queries on `triax/<building>/calibration/push/<sensor>` (answered by the queryable that
//! `serve` declares, with a copy of each acknowledgement put on
//! `triax/<building>/calibration/ack/<sensor>`), and catch-up from the lab's registry
//! ([`super::catchup`]). A record is applied by either path only if, in this order:
//!
//! 1. its signature verifies under one of the trusted lab keys (`unknown_key`, `bad_signature`,
//!    `malformed`);
//! 2. for a push, its sensor is the sensor named by the key (`wrong_sensor`);
//! 3. it loads into a [`Corrector`] (`invalid_record`);
//! 4. its version is not below the version in force, and the store accepts it: newer, or the
//!    same version with identical content, an idempotent retry (`stale_version` otherwise: a
//!    replay of an older record, or a different record under a version already used);
//! 5. the store made it durable (`store_failure` otherwise).
//!
//! Only then is the corrector installed, with one atomic swap ([`SensorTable::install`]): every
//! batch is corrected wholly with the old or wholly with the new calibration, and the first batch
//! taken after the swap uses the new one. The acknowledgement is sent after the swap, so
//! `accepted` means durable and in force.
//!
//! Updates are serialised by one lock (they are rare), so two pushes for one sensor cannot install
//! out of order. The sample path never takes that lock.

use std::sync::atomic::Ordering::Relaxed;
use std::sync::Arc;

use time::OffsetDateTime;
use tokio::task::JoinHandle;
use triax_calibration::corrector::Corrector;
use triax_calibration_store::{PutOutcome, Rejection, Store, StoreError};
use triax_protocol::keys::{self, Stream};
use triax_protocol::messages::{PushAck, PushOutcome, RefusalReason, SignedRecord};
use triax_protocol::signing::TrustedKeys;
use triax_protocol::{from_json, to_json, BuildingId, Key, SensorId, JSON_FORMAT_VERSION};

use super::{Context, Task};
use crate::error::{zenoh_err, GatewayError};
use crate::shutdown::Shutdown;
use crate::state::{GatewayCounters, SensorTable, Signer};

/// Which path a record came by, for logs.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Source {
    /// A push from the lab, acknowledged to it.
    Push,
    /// A record served by the lab's registry on catch-up.
    CatchUp,
}

impl std::fmt::Display for Source {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Source::Push => "push",
            Source::CatchUp => "catch-up",
        })
    }
}

/// Applies signed calibration records to one gateway's store and sensor table.
pub struct Updater {
    building: BuildingId,
    gateway_name: String,
    trusted: TrustedKeys,
    store: Arc<Store>,
    table: Arc<SensorTable>,
    counters: Arc<GatewayCounters>,
    /// Held from the version check to the swap: the version in force is always the highest one
    /// made durable.
    update_lock: tokio::sync::Mutex<()>,
}

fn refused(reason: RefusalReason, detail: impl Into<String>) -> PushOutcome {
    PushOutcome::Refused {
        reason,
        detail: detail.into(),
    }
}

impl Updater {
    pub fn new(
        building: BuildingId,
        gateway_name: String,
        trusted: TrustedKeys,
        store: Arc<Store>,
        table: Arc<SensorTable>,
        counters: Arc<GatewayCounters>,
    ) -> Updater {
        Updater {
            building,
            gateway_name,
            trusted,
            store,
            table,
            counters,
            update_lock: tokio::sync::Mutex::new(()),
        }
    }

    pub fn building(&self) -> &BuildingId {
        &self.building
    }

    pub fn table(&self) -> &Arc<SensorTable> {
        &self.table
    }

    /// Decodes a push payload and applies it; `sensor` is the sensor named by the push key.
    pub async fn apply_payload(&self, sensor: &SensorId, payload: &[u8]) -> PushOutcome {
        match from_json::<SignedRecord>(payload) {
            Ok(signed) => self.apply(Source::Push, Some(sensor), &signed).await,
            Err(e) => {
                let outcome = refused(RefusalReason::Malformed, e.to_string());
                self.count(Source::Push, Some(sensor), &outcome);
                outcome
            }
        }
    }

    /// Verifies, validates, stores and installs one signed record (see the module doc for the
    /// order of the checks). `expected`: the sensor the record must be for (a push's key).
    pub async fn apply(
        &self,
        source: Source,
        expected: Option<&SensorId>,
        signed: &SignedRecord,
    ) -> PushOutcome {
        let outcome = self.decide(expected, signed).await;
        self.count(source, expected, &outcome);
        outcome
    }

    fn count(&self, source: Source, sensor: Option<&SensorId>, outcome: &PushOutcome) {
        let sensor = sensor.map_or("-", |s| s.as_str());
        match outcome {
            PushOutcome::Accepted {
                version,
                already_stored,
            } => {
                self.counters.pushes_accepted.fetch_add(1, Relaxed);
                tracing::info!(%source, sensor, version, already_stored, "calibration accepted");
            }
            PushOutcome::Refused { reason, detail } => {
                self.counters.pushes_refused.fetch_add(1, Relaxed);
                tracing::warn!(%source, sensor, ?reason, %detail, "calibration refused");
            }
        }
    }

    async fn decide(&self, expected: Option<&SensorId>, signed: &SignedRecord) -> PushOutcome {
        let record = match self.trusted.verify(signed) {
            Ok(r) => r,
            Err(e) => return refused(e.refusal_reason(), e.to_string()),
        };
        if let Some(sensor) = expected {
            if &record.sensor_id != sensor {
                return refused(
                    RefusalReason::WrongSensor,
                    format!(
                        "the record is for sensor {}, pushed on the key of sensor {sensor}",
                        record.sensor_id
                    ),
                );
            }
        }
        let corrector = match Corrector::from_record(&record) {
            Ok(c) => c,
            Err(e) => return refused(RefusalReason::InvalidRecord, e.to_string()),
        };
        let version = record.version;
        let health = self.table.health_seed(&record, &corrector);
        let _guard = self.update_lock.lock().await;
        let in_force = self.version_in_force(&record.sensor_id);
        if let Some(current) = in_force.filter(|&c| version < c) {
            return refused(
                RefusalReason::StaleVersion,
                format!(
                    "version {version} is older than version {current} in force: a replay; a \
                     rollback is issued as a new, higher version"
                ),
            );
        }
        let store = self.store.clone();
        // The store's current version, not only the one in force, bounds what may be
        // installed: a sensor whose current record could not be loaded at start has nothing in
        // force, and the store answers "already stored" for any identical older version (so
        // that re-importing a backup is idempotent), which a push must not take as current.
        let stored =
            tokio::task::spawn_blocking(move || -> Result<bool, (RefusalReason, String)> {
                let store_failure = |e: StoreError| {
                    tracing::error!(cause = %e, "calibration store failed");
                    (RefusalReason::StoreFailure, e.to_string())
                };
                match store
                    .current_version(&record.sensor_id)
                    .map_err(store_failure)?
                {
                    Some(current) if record.version < current => Err((
                        RefusalReason::StaleVersion,
                        format!(
                            "version {} is older than version {current} in the store: a replay; a \
                         rollback is issued as a new, higher version",
                            record.version
                        ),
                    )),
                    _ => match store.put(&record).map_err(store_failure)? {
                        Ok(PutOutcome::Stored | PutOutcome::Repaired) => Ok(false),
                        Ok(PutOutcome::AlreadyStored) => Ok(true),
                        Err(Rejection::Invalid(e)) => {
                            Err((RefusalReason::InvalidRecord, e.to_string()))
                        }
                        Err(r @ (Rejection::Stale { .. } | Rejection::Conflict { .. })) => {
                            Err((RefusalReason::StaleVersion, r.to_string()))
                        }
                    },
                }
            })
            .await;
        let already_stored = match stored {
            Ok(Ok(already_stored)) => already_stored,
            Ok(Err((reason, detail))) => return refused(reason, detail),
            Err(e) => return refused(RefusalReason::StoreFailure, format!("store task: {e}")),
        };
        // An identical record already in force needs no swap; one stored but not in force (it
        // was made durable just before a crash, say) is installed now.
        if !(already_stored && in_force == Some(version)) {
            let sensor = corrector.sensor_id().clone();
            let replaced = self.table.install(corrector, health);
            tracing::info!(
                building = %self.building,
                sensor = %sensor,
                version,
                replaced = ?replaced,
                "calibration swapped in"
            );
        }
        PushOutcome::Accepted {
            version,
            already_stored,
        }
    }

    fn version_in_force(&self, sensor: &SensorId) -> Option<u64> {
        // Updates are rare; a scan of the versions in force costs nothing next to the fsync,
        // and unlike `entry` it does not create a table entry for a sensor never seen.
        self.table
            .versions()
            .into_iter()
            .find_map(|(s, v)| (&s == sensor).then_some(v))
    }

    /// The acknowledgement of `outcome` for `sensor`.
    pub fn ack(&self, sensor: &SensorId, outcome: PushOutcome) -> PushAck {
        PushAck {
            format_version: JSON_FORMAT_VERSION,
            building: self.building.clone(),
            sensor_id: sensor.clone(),
            gateway: self.gateway_name.clone(),
            outcome,
            at: OffsetDateTime::now_utc(),
        }
    }
}

/// Declares the push queryable on `triax/<building>/calibration/push/*` and answers pushes
/// until `shutdown`.
pub(crate) async fn serve(
    session: zenoh::Session,
    updater: Arc<Updater>,
    signer: Arc<Signer>,
    mut shutdown: Shutdown,
) -> Result<JoinHandle<()>, zenoh::Error> {
    let building = updater.building().clone();
    let queryable = session
        .declare_queryable(keys::all_sensors(&building, Stream::CalibrationPush))
        .await?;
    if updater.trusted.is_empty() {
        tracing::warn!(
            building = %building,
            "no trusted lab keys configured: every calibration push and registry record will be \
             refused with unknown_key (set calibration.trusted_lab_keys)"
        );
    } else {
        tracing::info!(building = %building, trusted_lab_keys = updater.trusted.len(),
            "accepting signed calibration pushes");
    }
    Ok(tokio::spawn(async move {
        loop {
            let query = tokio::select! {
                q = queryable.recv_async() => match q { Ok(q) => q, Err(_) => break },
                _ = shutdown.recv() => break,
            };
            answer(&session, &updater, &signer, query).await;
        }
    }))
}

async fn answer(
    session: &zenoh::Session,
    updater: &Updater,
    signer: &Signer,
    query: zenoh::query::Query,
) {
    let sensor = match Key::parse(query.key_expr().as_str()) {
        Ok(Key::CalibrationPush(b, s)) if &b == updater.building() => s,
        // The queryable's key expression admits only this building's push keys, but a chunk
        // that is not a valid id (`@x`, say) still matches `*`.
        other => {
            updater.counters.pushes_refused.fetch_add(1, Relaxed);
            let detail = match other {
                Err(e) => e.to_string(),
                Ok(k) => format!("{k} is not a push key of building {}", updater.building()),
            };
            tracing::warn!(key = %query.key_expr(), %detail, "push refused: malformed key");
            if let Err(e) = query.reply_err(detail).await {
                tracing::warn!(cause = %e, "push error reply failed");
            }
            return;
        }
    };
    let outcome = match query.payload() {
        Some(p) => updater.apply_payload(&sensor, &p.to_bytes()).await,
        None => {
            let outcome = refused(
                RefusalReason::Malformed,
                "the push query carries no payload",
            );
            updater.count(Source::Push, Some(&sensor), &outcome);
            outcome
        }
    };
    let body = to_json(&updater.ack(&sensor, outcome));
    let b = updater.building().clone();
    let reply_key = Key::CalibrationPush(b.clone(), sensor.clone()).to_string();
    let reply = query
        .reply(&reply_key, body.clone())
        .attachment(signer.attachment(&reply_key, "", &body));
    if let Err(e) = reply.await {
        tracing::warn!(sensor = %sensor, cause = %e, "push reply failed");
    }
    // Finalise the query before the copy: the pusher waits for the final, monitors do not.
    drop(query);
    let ack_key = Key::CalibrationAck(b, sensor.clone()).to_string();
    let put = session
        .put(&ack_key, &body[..])
        .attachment(signer.attachment(&ack_key, "", &body));
    if let Err(e) = put.await {
        tracing::warn!(sensor = %sensor, cause = %e, "push ack copy failed");
    }
}

/// Starts the push queryable; returns the updater, which the catch-up shares.
pub async fn start(ctx: &Context) -> Result<(Arc<Updater>, Task), GatewayError> {
    let config = &ctx.config;
    let updater = Arc::new(Updater::new(
        config.building.clone(),
        config.gateway_name.clone(),
        TrustedKeys::new(config.calibration.trusted_lab_keys.clone()),
        ctx.store.clone(),
        ctx.table.clone(),
        ctx.counters.clone(),
    ));
    let task = serve(
        ctx.session.clone(),
        updater.clone(),
        ctx.signer.clone(),
        ctx.shutdown.clone(),
    )
    .await
    .map_err(zenoh_err("declare the calibration push queryable"))?;
    Ok((updater, task))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::config::Config;
    use triax_protocol::record::sample;
    use triax_protocol::signing::{sign, LabSigningKey};

    /// A key from a fixed seed: the tests need no randomness.
    fn key(seed: u8) -> LabSigningKey {
        LabSigningKey::from_bytes(&[seed; 32])
    }

    struct Fixture {
        _dir: tempfile::TempDir,
        updater: Updater,
        counters: Arc<GatewayCounters>,
    }

    fn fixture() -> Fixture {
        let dir = tempfile::tempdir().unwrap();
        let config = Arc::new(Config::for_tests("b1", dir.path(), vec![]));
        let store = Arc::new(Store::open(dir.path().join("store")).unwrap());
        let counters = Arc::new(GatewayCounters::default());
        let updater = Updater::new(
            config.building.clone(),
            "gw".into(),
            TrustedKeys::new(vec![key(1).verifying_key()]),
            store,
            Arc::new(SensorTable::new(config)),
            counters.clone(),
        );
        Fixture {
            _dir: dir,
            updater,
            counters,
        }
    }

    fn s(id: &str) -> SensorId {
        SensorId::new(id).unwrap()
    }

    fn reason(o: &PushOutcome) -> Option<RefusalReason> {
        match o {
            PushOutcome::Refused { reason, .. } => Some(*reason),
            PushOutcome::Accepted { .. } => None,
        }
    }

    #[tokio::test]
    async fn accepts_then_refuses_replays_and_forgeries() {
        let f = fixture();
        let u = &f.updater;
        let v2 = sign(&sample::record("acc-1", 2), &key(1));
        let v3 = sign(&sample::record("acc-1", 3), &key(1));
        let push = |signed: SignedRecord| async move {
            u.apply_payload(&s("acc-1"), &to_json(&signed)).await
        };
        assert_eq!(
            push(v2.clone()).await,
            PushOutcome::Accepted {
                version: 2,
                already_stored: false
            }
        );
        assert_eq!(u.version_in_force(&s("acc-1")), Some(2));
        assert_eq!(
            push(v2.clone()).await,
            PushOutcome::Accepted {
                version: 2,
                already_stored: true
            },
            "an idempotent retry"
        );
        assert!(matches!(
            push(v3).await,
            PushOutcome::Accepted { version: 3, .. }
        ));
        assert_eq!(
            reason(&push(v2).await),
            Some(RefusalReason::StaleVersion),
            "replay of an older, stored record"
        );
        let mut other = sample::record("acc-1", 3);
        other.dynamic.offset[0] += 0.1;
        assert_eq!(
            reason(&push(sign(&other, &key(1))).await),
            Some(RefusalReason::StaleVersion),
            "same version, other content"
        );
        assert_eq!(
            reason(&push(sign(&sample::record("acc-1", 4), &key(2))).await),
            Some(RefusalReason::UnknownKey)
        );
        let mut tampered = sign(&sample::record("acc-1", 4), &key(1));
        tampered.record_json = tampered
            .record_json
            .replace("\"version\":4", "\"version\":5");
        assert_eq!(
            reason(&push(tampered).await),
            Some(RefusalReason::BadSignature)
        );
        assert_eq!(
            reason(&push(sign(&sample::record("acc-2", 4), &key(1))).await),
            Some(RefusalReason::WrongSensor)
        );
        let mut singular = sample::record("acc-1", 4);
        singular.dynamic.sensitivity = [[1.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]];
        assert_eq!(
            reason(&push(sign(&singular, &key(1))).await),
            Some(RefusalReason::InvalidRecord)
        );
        assert_eq!(
            reason(&u.apply_payload(&s("acc-1"), b"{").await),
            Some(RefusalReason::Malformed)
        );
        assert_eq!(u.version_in_force(&s("acc-1")), Some(3));
        assert_eq!(f.counters.pushes_accepted.load(Relaxed), 3);
        assert_eq!(f.counters.pushes_refused.load(Relaxed), 7);
        assert_eq!(u.table().len(), 1, "refused pushes add no sensor");
    }

    #[tokio::test]
    async fn no_trusted_keys_refuses_everything_as_unknown_key() {
        let dir = tempfile::tempdir().unwrap();
        let config = Arc::new(Config::for_tests("b1", dir.path(), vec![]));
        let u = Updater::new(
            config.building.clone(),
            "gw".into(),
            TrustedKeys::default(),
            Arc::new(Store::open(dir.path().join("store")).unwrap()),
            Arc::new(SensorTable::new(config)),
            Arc::new(GatewayCounters::default()),
        );
        let signed = sign(&sample::record("acc-1", 1), &key(1));
        let o = u.apply(Source::CatchUp, None, &signed).await;
        assert_eq!(reason(&o), Some(RefusalReason::UnknownKey));
    }

    /// A sensor whose current record is stored but not in force (it failed to load at start)
    /// must not be rolled back by a replay of an older record the store still holds.
    #[tokio::test]
    async fn a_replay_cannot_roll_back_a_sensor_with_nothing_in_force() {
        let f = fixture();
        let u = &f.updater;
        let v1 = sign(&sample::record("acc-1", 1), &key(1));
        for version in [1, 2] {
            u.store
                .put(&sample::record("acc-1", version))
                .unwrap()
                .unwrap();
        }
        assert_eq!(u.version_in_force(&s("acc-1")), None);
        let outcome = u.apply_payload(&s("acc-1"), &to_json(&v1)).await;
        assert_eq!(
            reason(&outcome),
            Some(RefusalReason::StaleVersion),
            "{outcome:?}"
        );
        assert_eq!(
            u.version_in_force(&s("acc-1")),
            None,
            "nothing was installed"
        );
    }
}
