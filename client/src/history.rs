//! History queries (PROTOCOL.md §5.1): one sensor's or many sensors' kept batches, corrected
//! again by the gateway, fetched page by page.
//!
//! With trusted gateway keys ([`HistoryRequest::trusted`]) every query carries a fresh nonce
//! and only the batches a seal signed for that nonce lists are handed over (PROTOCOL.md §6):
//! any peer can answer a query, and its replies are counted ([`unverified_replies`]) and
//! dropped.

use std::collections::HashSet;
use std::sync::atomic::{AtomicU64, Ordering::Relaxed};
use std::sync::Arc;
use std::time::Duration;

use triax_protocol::batch::CorrectedBatch;
use triax_protocol::provenance::{digest, is_seal, verify_message, Digest, GatewayKeys, Seal};
use triax_protocol::{BuildingId, Key, SensorId};
use zenoh::query::ConsolidationMode;

use crate::{zenoh_err, ClientError};

/// Largest page asked for.
const PAGE: usize = 10_000;

/// What to ask a gateway's history for.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct HistoryRequest {
    pub building: BuildingId,
    /// A sensor id, or a key-expression chunk such as `*`.
    pub sensors: String,
    pub from_ns: Option<i64>,
    pub to_ns: Option<i64>,
    pub from_seq: Option<u64>,
    pub to_seq: Option<u64>,
    /// `in_force` (default), `latest` or a version number.
    pub calibration: Option<String>,
    /// Whose seals make a reply the gateway's; `None`: every reply is taken on trust.
    pub trusted: Option<Arc<GatewayKeys>>,
}

impl HistoryRequest {
    /// Every kept batch of one sensor.
    pub fn sensor(building: &BuildingId, sensor: &SensorId) -> HistoryRequest {
        HistoryRequest {
            building: building.clone(),
            sensors: sensor.to_string(),
            from_ns: None,
            to_ns: None,
            from_seq: None,
            to_seq: None,
            calibration: None,
            trusted: None,
        }
    }

    fn selector(&self, limit: usize, after: Option<&str>, nonce: Option<&str>) -> String {
        let key = match SensorId::new(self.sensors.as_str()) {
            Ok(s) => Key::History(self.building.clone(), s).to_string(),
            // A wildcard chunk: the key module builds only concrete keys.
            Err(_) => format!("triax/{}/history/{}", self.building, self.sensors),
        };
        let mut p = vec![format!("limit={limit}")];
        let fields = [
            ("from_ns", self.from_ns.map(|v| v.to_string())),
            ("to_ns", self.to_ns.map(|v| v.to_string())),
            ("from_seq", self.from_seq.map(|v| v.to_string())),
            ("to_seq", self.to_seq.map(|v| v.to_string())),
            ("calibration", self.calibration.clone()),
            ("after", after.map(str::to_owned)),
            ("nonce", nonce.map(str::to_owned)),
        ];
        for (name, v) in fields {
            if let Some(v) = v {
                p.push(format!("{name}={v}"));
            }
        }
        format!("{key}?{}", p.join(";"))
    }
}

/// Whether the history holds at least one batch `request` selects (one batch asked for).
pub async fn any_kept(
    session: &zenoh::Session,
    request: &HistoryRequest,
    timeout: Duration,
) -> Result<bool, ClientError> {
    let (n, _) = page(session, request, 1, None, timeout, &mut |_| {}).await?;
    Ok(n > 0)
}

/// One batch read back from a history: its payload as the gateway sent it, decoded.
#[derive(Debug, Clone, PartialEq)]
pub struct Recovered {
    pub payload: Vec<u8>,
    pub batch: CorrectedBatch,
}

/// Reads every batch `request` selects, page by page, handing each to `each` in the order the
/// gateway sends them (sensor by sensor, in arrival order). Returns how many.
///
/// Zenoh ends a query without an error when the link its replies travel on closes (a consumer
/// that stalled longer than the sending side's `wait_before_close`, 5 s by default), so an
/// answer shorter than its limit does not prove that the history has no more: the next page is
/// asked for after the last cursor until one holds nothing.
pub async fn fetch(
    session: &zenoh::Session,
    request: &HistoryRequest,
    timeout: Duration,
    each: &mut (dyn FnMut(Recovered) + Send),
) -> Result<usize, ClientError> {
    let mut total = 0;
    let mut after: Option<String> = None;
    loop {
        let (in_page, last) = page(session, request, PAGE, after.as_deref(), timeout, each).await?;
        // A cursor that does not move on (a peer answering every query with the same reply,
        // when nothing is verified) would ask forever.
        let stuck = last == after;
        after = last;
        total += in_page;
        if in_page == 0 || after.is_none() || stuck {
            return Ok(total);
        }
    }
}

/// History replies dropped since the process started because no seal of the gateway listed
/// them (a peer's answers, or a gateway's whose key is not trusted).
pub fn unverified_replies() -> u64 {
    UNVERIFIED.load(Relaxed)
}

static UNVERIFIED: AtomicU64 = AtomicU64::new(0);

/// Replies of one verified answer waiting for the seal that lists them.
struct Unsealed {
    trusted: Arc<GatewayKeys>,
    nonce: String,
    waiting: Vec<(Digest, Recovered, Option<String>)>,
    /// The first refusal of the gateway: shown when nothing verified came.
    error: Option<String>,
}

impl Unsealed {
    /// A verified seal hands over what it lists, in the answer's order; the rest was not the
    /// gateway's.
    fn seal(
        &mut self,
        listed: &[Digest],
        n: &mut usize,
        after: &mut Option<String>,
        each: &mut (dyn FnMut(Recovered) + Send),
    ) {
        let listed: HashSet<&Digest> = listed.iter().collect();
        for (d, recovered, cursor) in self.waiting.drain(..) {
            if listed.contains(&d) {
                *n += 1;
                *after = cursor;
                each(recovered);
            } else {
                UNVERIFIED.fetch_add(1, Relaxed);
            }
        }
    }
}

/// One answer of the history query `selector`: how many batches it held, each handed to `each`,
/// and the cursor of the last one.
async fn page(
    session: &zenoh::Session,
    request: &HistoryRequest,
    limit: usize,
    after_cursor: Option<&str>,
    timeout: Duration,
    each: &mut (dyn FnMut(Recovered) + Send),
) -> Result<(usize, Option<String>), ClientError> {
    let mut unsealed = request.trusted.clone().map(|trusted| Unsealed {
        trusted,
        nonce: triax_protocol::provenance::fresh_nonce(),
        waiting: Vec::new(),
        error: None,
    });
    let nonce = unsealed.as_ref().map(|u| u.nonce.as_str());
    let selector = request.selector(limit, after_cursor, nonce);
    let failed = |message: String| ClientError::History {
        selector: selector.clone(),
        message,
    };
    let replies = session
        .get(&selector)
        .consolidation(ConsolidationMode::None)
        .timeout(timeout)
        .await
        .map_err(zenoh_err("history query"))?;
    let (mut n, mut after) = (0, None);
    while let Ok(reply) = replies.recv_async().await {
        let sample = match (reply.result(), unsealed.as_mut()) {
            (Ok(sample), _) => sample,
            (Err(e), None) => {
                return Err(failed(
                    String::from_utf8_lossy(&e.payload().to_bytes()).into_owned(),
                ))
            }
            // A refusal cannot be signed: any peer can send one. It stands only if nothing
            // the gateway signed came.
            (Err(e), Some(u)) => {
                u.error.get_or_insert_with(|| {
                    String::from_utf8_lossy(&e.payload().to_bytes()).into_owned()
                });
                continue;
            }
        };
        let payload = sample.payload().to_bytes().to_vec();
        let attachment = sample.attachment().map(|a| a.to_bytes().into_owned());
        let Some(u) = unsealed.as_mut() else {
            let batch = CorrectedBatch::decode(&payload)
                .map_err(|e| failed(format!("a reply does not decode: {e}")))?;
            after = attachment.map(|a| String::from_utf8_lossy(&a).into_owned());
            n += 1;
            each(Recovered { payload, batch });
            continue;
        };
        let key = sample.key_expr().as_str();
        if is_seal(&payload) {
            let verified =
                verify_message(&u.trusted, key, &u.nonce, &payload, attachment.as_deref())
                    .ok()
                    .and_then(|_| Seal::decode(&payload).ok());
            match verified {
                Some(seal) => u.seal(&seal.digests, &mut n, &mut after, each),
                None => {
                    UNVERIFIED.fetch_add(1, Relaxed);
                }
            }
            continue;
        }
        let Ok(batch) = CorrectedBatch::decode(&payload) else {
            UNVERIFIED.fetch_add(1, Relaxed);
            continue;
        };
        let cursor = attachment.as_deref().unwrap_or_default();
        let d = digest(key, cursor, &payload);
        let cursor = attachment.map(|a| String::from_utf8_lossy(&a).into_owned());
        u.waiting.push((d, Recovered { payload, batch }, cursor));
    }
    if let Some(u) = unsealed {
        if !u.waiting.is_empty() {
            UNVERIFIED.fetch_add(u.waiting.len() as u64, Relaxed);
            tracing::warn!(
                selector = %selector,
                replies = u.waiting.len(),
                "history replies no seal of the gateway listed were dropped"
            );
        }
        if let (0, Some(e)) = (n, u.error) {
            return Err(failed(e));
        }
    }
    Ok((n, after))
}

#[cfg(test)]
mod tests {
    use std::sync::atomic::{AtomicUsize, Ordering::Relaxed};
    use std::sync::Arc;

    use triax_net::{ZenohMode, ZenohSettings};
    use triax_test_support::free_port;
    use zenoh::Wait;

    use super::*;

    fn batch(sequence: u64) -> CorrectedBatch {
        let mut b = crate::follow::tests::batch(sequence, sequence as i64, 0);
        b.header.sensor_id = SensorId::new("acc-01").unwrap();
        b
    }

    /// A history whose first answer ends after three of its five batches, as one whose link
    /// closed mid-answer does: the fetch asks again after the third and gets the other two.
    #[tokio::test(flavor = "multi_thread", worker_threads = 2)]
    async fn an_answer_cut_short_is_continued_after_its_last_cursor() {
        let endpoint = format!("tcp/127.0.0.1:{}", free_port());
        let open = |listen: Vec<String>, connect: Vec<String>| async move {
            let config = ZenohSettings::loopback(ZenohMode::Peer, listen, connect)
                .to_config()
                .unwrap();
            zenoh::open(config).await.unwrap()
        };
        let gateway = open(vec![endpoint.clone()], vec![]).await;
        let queries = Arc::new(AtomicUsize::new(0));
        let counted = queries.clone();
        let _history = gateway
            .declare_queryable("triax/hq/history/acc-01")
            .callback(move |q| {
                counted.fetch_add(1, Relaxed);
                let params = q.parameters().as_str().to_owned();
                let after: u64 = params
                    .split(';')
                    .find_map(|p| p.strip_prefix("after=acc-01:"))
                    .map_or(0, |v| v.parse::<u64>().unwrap() + 1);
                // The first answer stops short of its limit with two batches left.
                let end = if after == 0 { 3 } else { 5 };
                for seq in after..end {
                    q.reply(q.key_expr().clone(), batch(seq).encode())
                        .attachment(format!("acc-01:{seq}"))
                        .wait()
                        .unwrap();
                }
            })
            .await
            .unwrap();
        let consumer = open(vec![], vec![endpoint]).await;
        let request = HistoryRequest::sensor(
            &BuildingId::new("hq").unwrap(),
            &SensorId::new("acc-01").unwrap(),
        );
        // The consumer's link may take a moment to reach the queryable.
        let deadline = std::time::Instant::now() + Duration::from_secs(60);
        let mut got = Vec::new();
        while got.is_empty() {
            assert!(std::time::Instant::now() < deadline, "no answer");
            got.clear();
            fetch(&consumer, &request, Duration::from_secs(10), &mut |r| {
                got.push(r.batch.header.sequence)
            })
            .await
            .unwrap();
        }
        assert_eq!(got, vec![0, 1, 2, 3, 4]);
        // The third query found nothing after the last batch: that is the end.
        assert!(queries.load(Relaxed) >= 3, "{}", queries.load(Relaxed));
    }
}
