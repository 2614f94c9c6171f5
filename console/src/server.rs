//! The console's routes: the page, its JSON, the history view and the live event stream.
//!
//! | path | answer |
//! |---|---|
//! | `/` | the page (`index.html`; the views are chosen by the URL's fragment) |
//! | `/app.js`, `/app.css`, `/favicon.svg` | its script, style and icon, embedded in the binary |
//! | `/api/me` | who the request comes from, and whether a login is needed |
//! | `POST /api/login`, `/api/logout` | a session cookie for an operator's name and password, and its end ([`crate::operators`]) |
//! | `/api/fleet[?building=[&sensor=]]` | the fleet view as JSON ([`crate::fleet::Snapshot`]), or one building's (one sensor's) row with its counters |
//! | `/api/alerts[?id=&building=&sensor=&kind=&level=&state=&from_ns=&to_ns=&limit=]` | the alert log, filtered, newest first |
//! | `/api/silences` | the silences kept, newest first |
//! | `POST /api/alerts/ack`, `/api/alerts/silence`, `/api/alerts/lift` | acknowledge alerts, silence or lift a silence (JSON body; role operate) |
//! | `POST /api/health/clear` | clear a field-health latch (role admin): not available yet, 501 |
//! | `/api/notifications` | what the notifications sent ([`crate::notify`]) |
//! | `/api/annotations?building=[&from_ns=&to_ns=&format=csv]`, `POST /api/annotations`, `POST /api/annotations/delete` | the operators' annotations ([`crate::annotations`]) |
//! | `/api/processed?building=&sensor=&from_ns=&to_ns=[&width=&quantity=&band=]` | band-passed acceleration, velocity or displacement, up to 1 h ([`crate::process`]) |
//! | `/api/helicorder?building=&sensor=&from_ns=&to_ns=[&axis=&row_s=]` | up to 24 h of one axis in rows ([`crate::helicorder`]) |
//! | `/api/modes?building=` | the building's modes heard since the console started: per track its frequency trend with its band, the latest window's modes and shapes ([`crate::modes`]) |
//! | `/api/sensor?building=&sensor=` | the sensor's status and calibration record, asked of its gateway |
//! | `/api/history?building=&sensor=&from_ns=&to_ns=&width=[&calibration=]` | a past range, decimated |
//! | `/api/trend?building=&sensor=&from_ns=&to_ns=` | per-minute aggregates, up to 7 days ([`crate::trend`]) |
//! | `/api/spectrum?building=&sensor=&from_ns=&to_ns=[&segment=]` | PSD per axis with its band, up to 1 h ([`crate::spectrum`]) |
//! | `/api/spectrogram?building=&sensor=&from_ns=&to_ns=[&axis=&segment=&columns=]` | one axis's PSD per column of time, up to 1 h ([`crate::spectrum::Spectrogram`]) |
//! | `/api/export.csv?building=&sensor=&from_ns=&to_ns=` | every sample of up to 1 h, as CSV |
//! | `/api/export.mseed?building=&sensor=&from_ns=&to_ns=[&network=]` | every calibrated sample of up to 1 h, as miniSEED 2 |
//! | `/events[?building=&sensor=&span_s=&width=&lite=]` | Server-Sent Events: `fleet` once, then `fleet_delta` every second; with a sensor, `live` and `tilt` |
//!
//! Anything else is 404; an unknown or malformed parameter or body field is 400 naming it.
//! Once operator accounts exist (or a proxy names operators), every route but the page's files and
//! `/api/me` needs a logged-in operator (401). `POST` is answered on the write routes only (405 elsewhere, and 405 to a `GET` there),
//! and only with a JSON body (`Content-Type: application/json`, 415 otherwise) and an `Origin`,
//! if sent, that is the console's own (`http://` and the request's `Host`; 403 otherwise): a
//! page elsewhere can neither send such a request without a CORS preflight, which the console
//! never grants, nor pass the origin check.

use std::sync::Arc;
use std::time::Duration;

use tokio::net::TcpStream;
use tokio::sync::{watch, OwnedSemaphorePermit, Semaphore};
use triax_client::HistoryRequest;
use triax_protocol::messages::{AlertLevel, GatewayStatus};
use triax_protocol::{from_json, BuildingId, Key, SensorId};

use crate::alertlog::{AlertQuery, LevelFilter, StateFilter};
use crate::buckets::{Aggregator, View, MAX_BUCKETS};
use crate::fleet::{Fleet, GatewayState};
use crate::http::{self, Refusal, Request};
use crate::live::{Feeds, KEEP_NS};
use crate::operators::{Login, Operator, Operators, Role};
use crate::provenance::Provenance;
use crate::ConsoleOptions;

const INDEX_HTML: &str = include_str!("assets/index.html");
const APP_JS: &str = include_str!("assets/app.js");
const APP_CSS: &str = include_str!("assets/app.css");
const FAVICON_SVG: &str = include_str!("assets/favicon.svg");

/// Longest range one history view reads.
pub const MAX_HISTORY_SPAN_NS: i64 = 3600 * 1_000_000_000;
/// History read before the range, for a batch that straddles its start and for gap detection.
const HISTORY_LEAD_NS: i64 = 60 * 1_000_000_000;
/// Time between live frames.
const LIVE_PERIOD: Duration = Duration::from_millis(250);
/// Each live frame repeats this much of the stream, so a late batch still reaches the page.
const RESEND_NS: i64 = 2_000_000_000;
/// Time between live frames of a light stream (`lite=1`).
const LITE_PERIOD: Duration = Duration::from_secs(1);
/// Time between fleet events of a light stream.
const LITE_FLEET_PERIOD: Duration = Duration::from_secs(5);
/// Plot widths accepted, in buckets (pixel columns).
const WIDTH_RANGE: std::ops::RangeInclusive<i64> = 50..=4000;

/// What every connection shares.
pub struct Context {
    pub session: zenoh::Session,
    pub fleet: Arc<Fleet>,
    pub feeds: Feeds,
    pub fleet_events: Arc<crate::FleetEvents>,
    pub options: ConsoleOptions,
    pub streams: Arc<Semaphore>,
    pub history_queries: Arc<Semaphore>,
    pub stop: watch::Receiver<bool>,
    pub trends: tokio::sync::Mutex<crate::trend::TrendCache>,
    /// The buildings' modes heard on `triax/*/modes`.
    pub modes: Arc<std::sync::Mutex<crate::modes::ModesBook>>,
    /// The operators' accounts and sessions.
    pub operators: Arc<Operators>,
    /// Password checks at once (each is an Argon2 hash: tens of milliseconds and 19 MiB).
    pub logins: Arc<Semaphore>,
    /// The notifications' queue and what they sent.
    pub notifier: crate::notify::Notifier,
    /// The operators' annotations.
    pub annotations: std::sync::Mutex<crate::annotations::Annotations>,
    /// Per-second minima and maxima of the sensors whose helicorder was drawn.
    pub helicorder: tokio::sync::Mutex<crate::helicorder::SecondsCache>,
}

/// Password checks at once; more are answered 503.
pub const MAX_LOGINS_AT_ONCE: usize = 2;

/// How long a connection over the limit gets to send its request before its 503.
const BUSY_READ_TIMEOUT: Duration = Duration::from_secs(1);

/// Answers a connection over the limit with 503: its request is read first (briefly), so that
/// the answer is not lost to a reset.
pub async fn refuse_busy(mut stream: TcpStream, limit: usize, _permit: OwnedSemaphorePermit) {
    let _ = http::read_request_within(&mut stream, BUSY_READ_TIMEOUT).await;
    let r = Refusal::new(
        503,
        format!("too many connections at once ({limit}); try again in a moment"),
    );
    let _ = http::respond_error(&mut stream, &r).await;
}

/// Answers one connection.
pub async fn handle(ctx: Arc<Context>, mut stream: TcpStream, _permit: OwnedSemaphorePermit) {
    let req = match http::read_request(&mut stream).await {
        Ok(Some(r)) => r,
        Ok(None) => return,
        Err(refusal) => {
            let _ = http::respond_error(&mut stream, &refusal).await;
            return;
        }
    };
    if !ctx.options.allow_remote && !req.host.as_deref().is_some_and(http::is_loopback_host) {
        let r = Refusal::new(
            403,
            "the console answers only requests addressed to a loopback name (Host: 127.0.0.1, localhost or [::1])",
        );
        let _ = http::respond_error(&mut stream, &r).await;
        return;
    }
    if let Err(refusal) = route(&ctx, &mut stream, &req).await {
        let _ = http::respond_error(&mut stream, &refusal).await;
    }
}

/// The routes that write, the only ones that take `POST`, and the role each needs (none: any
/// visitor, for logging in and out).
const WRITE_ROUTES: [(&str, Option<Role>); 8] = [
    ("/api/login", None),
    ("/api/logout", None),
    ("/api/alerts/ack", Some(Role::Operate)),
    ("/api/alerts/silence", Some(Role::Operate)),
    ("/api/alerts/lift", Some(Role::Operate)),
    ("/api/annotations", Some(Role::Operate)),
    ("/api/annotations/delete", Some(Role::Operate)),
    ("/api/health/clear", Some(Role::Admin)),
];

/// What anyone may fetch before logging in: the page itself, and who they are.
const PUBLIC_ROUTES: [&str; 6] = [
    "/",
    "/index.html",
    "/app.js",
    "/app.css",
    "/favicon.svg",
    "/api/me",
];

/// Who sent `req`: a session's operator, or the trusted proxy header's.
fn operator_of(ctx: &Context, req: &Request) -> Option<Operator> {
    let header = ctx
        .operators
        .identity_header()
        .and_then(|name| req.header(name));
    ctx.operators.identify(req.cookie.as_deref(), header)
}

/// What `/api/me` answers, and the page carries from the start.
fn me_json(ctx: &Context, who: Option<&Operator>) -> serde_json::Value {
    serde_json::json!({
        "operator": who,
        "login_required": ctx.operators.login_required(),
        "accounts": ctx.operators.path().is_some() && !ctx.operators.accounts().is_empty(),
        "proxy_header": ctx.operators.identity_header(),
        "time_zone": ctx.options.time_zone.as_ref().map(|z| z.name()),
    })
}

/// `text` escaped for a double-quoted HTML attribute.
fn html_attribute(text: &str) -> String {
    let mut out = String::with_capacity(text.len());
    for c in text.chars() {
        match c {
            '&' => out.push_str("&amp;"),
            '"' => out.push_str("&quot;"),
            '\'' => out.push_str("&#39;"),
            '<' => out.push_str("&lt;"),
            '>' => out.push_str("&gt;"),
            c => out.push(c),
        }
    }
    out
}

/// Refuses a request whose operator may not do what `need` allows.
fn require(ctx: &Context, who: Option<&Operator>, need: Role, what: &str) -> Result<(), Refusal> {
    match who {
        Some(o) if o.role >= need => Ok(()),
        Some(o) => Err(Refusal::new(
            403,
            format!(
                "operator {:?} has the role {}: {what} needs {}",
                o.name,
                o.role.name(),
                need.name()
            ),
        )),
        None if ctx.operators.login_required() => Err(Refusal::new(
            401,
            format!("{what} needs a logged-in operator: log in first (POST /api/login)"),
        )),
        None => Err(Refusal::new(
            403,
            format!(
                "{what} needs a logged-in operator, and this console has no operator accounts: \
                 create one with `triax-console operator add NAME --role {}`",
                need.name()
            ),
        )),
    }
}

async fn route(ctx: &Arc<Context>, stream: &mut TcpStream, req: &Request) -> Result<(), Refusal> {
    let p = Params(&req.query);
    let who = operator_of(ctx, req);
    // `/api/annotations` is read with GET and written with POST; the others are POST only.
    let write_route = WRITE_ROUTES
        .iter()
        .find(|(r, _)| *r == req.path)
        .filter(|_| req.post || req.path != "/api/annotations");
    if let Some(&(_, need)) = write_route {
        if !req.post {
            return Err(Refusal::method(
                "POST",
                format!("{} takes POST only, with a JSON body", req.path),
            ));
        }
        p.only(&[])?;
        // The origin first: a page elsewhere learns nothing, not even whether one is logged in.
        let body = check_write(req)?;
        if let Some(need) = need {
            require(ctx, who.as_ref(), need, &format!("POST {}", req.path))?;
        }
        match req.path.as_str() {
            "/api/login" => return login(ctx, stream, &body).await,
            "/api/logout" => {
                Body(&body).only(&[])?;
                if let Some(t) = req
                    .cookie
                    .as_deref()
                    .and_then(crate::operators::session_token)
                {
                    ctx.operators.logout(t);
                }
                let _ = http::respond_setting_cookie(
                    stream,
                    "application/json",
                    b"{\"logged_out\":true}",
                    &crate::operators::clear_cookie(),
                )
                .await;
                return Ok(());
            }
            _ => {}
        }
        // `require` passed: there is an operator.
        let Some(who) = who else {
            return Err(Refusal::new(401, "log in first"));
        };
        let answer = write(ctx, req, &body, &who)?;
        let _ = http::respond(stream, 200, "application/json", &json(&answer), false).await;
        return Ok(());
    }
    if ctx.operators.login_required()
        && who.is_none()
        && !PUBLIC_ROUTES.contains(&req.path.as_str())
    {
        return Err(Refusal::new(
            401,
            format!(
                "{} needs a logged-in operator: log in on the console's page (POST /api/login)",
                req.path
            ),
        ));
    }
    if req.post {
        return Err(Refusal::new(
            405,
            format!(
                "method \"POST\" not allowed on {:?}: it only reads (GET, HEAD)",
                req.path
            ),
        ));
    }
    let head_only = req.head_only;
    async fn ok(
        stream: &mut TcpStream,
        ty: &'static str,
        body: Vec<u8>,
        head_only: bool,
    ) -> Result<(), Refusal> {
        // A client that went away needs no answer.
        let _ = http::respond(stream, 200, ty, &body, head_only).await;
        Ok(())
    }
    const JSON: &str = "application/json";
    match req.path.as_str() {
        "/" | "/index.html" => {
            p.only(&[])?;
            // Who the page is for, in the page itself, so that it knows before its first
            // request whether to ask for a login (the cookie is HttpOnly: no script reads it).
            let me = html_attribute(&me_json(ctx, who.as_ref()).to_string());
            let page = INDEX_HTML.replacen(
                r#"<meta name="triax-me" content="">"#,
                &format!(r#"<meta name="triax-me" content="{me}">"#),
                1,
            );
            ok(stream, "text/html; charset=utf-8", page.into(), head_only).await
        }
        "/app.js" => {
            p.only(&[])?;
            ok(
                stream,
                "text/javascript; charset=utf-8",
                APP_JS.into(),
                head_only,
            )
            .await
        }
        "/app.css" => {
            p.only(&[])?;
            ok(stream, "text/css; charset=utf-8", APP_CSS.into(), head_only).await
        }
        "/favicon.svg" => {
            p.only(&[])?;
            ok(stream, "image/svg+xml", FAVICON_SVG.into(), head_only).await
        }
        "/api/me" => {
            p.only(&[])?;
            ok(stream, JSON, json(&me_json(ctx, who.as_ref())), head_only).await
        }
        "/api/fleet" => {
            p.only(&["building", "sensor"])?;
            if p.get("building").is_none() {
                if p.get("sensor").is_some() {
                    return Err(Refusal::new(400, "parameter \"sensor\" needs \"building\""));
                }
                return ok(stream, JSON, json(&ctx.fleet.snapshot()), head_only).await;
            }
            let b = p.building()?;
            let sensor = match p.get("sensor") {
                None => None,
                Some(_) => Some(p.sensor()?),
            };
            let Some(view) = ctx.fleet.building_snapshot(&b, sensor.as_ref()) else {
                return Err(Refusal::new(404, format!("no building {b} is known")));
            };
            ok(stream, JSON, json(&view), head_only).await
        }
        "/api/alerts" => {
            p.only(&[
                "id", "building", "sensor", "kind", "level", "state", "from_ns", "to_ns", "limit",
            ])?;
            let q = alert_query(&p)?;
            ok(
                stream,
                JSON,
                json(&ctx.fleet.with_log(|l| l.query(&q))),
                head_only,
            )
            .await
        }
        "/api/annotations" => {
            p.only(&["building", "from_ns", "to_ns", "format"])?;
            let b = p.building()?;
            let from_ns = p.int("from_ns", Some(0), 0..=i64::MAX)?;
            let to_ns = p.int("to_ns", Some(i64::MAX), 0..=i64::MAX)?;
            let (list, matched) = ctx
                .annotations
                .lock()
                .unwrap_or_else(|e| e.into_inner())
                .list(&b, from_ns, to_ns);
            match p.get("format").unwrap_or("json") {
                "json" => {
                    let body = serde_json::json!({ "annotations": list, "matched": matched, "max_listed": crate::annotations::MAX_LISTED });
                    ok(stream, JSON, json(&body), head_only).await
                }
                "csv" => {
                    let _ = http::respond_download(
                        stream,
                        "text/csv; charset=utf-8",
                        &format!("{b}_annotations.csv"),
                        crate::annotations::to_csv(&list).as_bytes(),
                        head_only,
                    )
                    .await;
                    Ok(())
                }
                v => Err(Refusal::new(
                    400,
                    format!("parameter \"format\": {v:?} is not json or csv"),
                )),
            }
        }
        "/api/notifications" => {
            p.only(&[])?;
            ok(stream, JSON, json(&ctx.notifier.view()), head_only).await
        }
        "/api/silences" => {
            p.only(&[])?;
            let now = time::OffsetDateTime::now_utc();
            ok(
                stream,
                JSON,
                json(&ctx.fleet.with_log(|l| l.silences(now))),
                head_only,
            )
            .await
        }
        "/api/modes" => {
            p.only(&["building"])?;
            let b = p.building()?;
            // A poisoned lock means a panic mid-update: what is there is still worth showing.
            let body = ctx.modes.lock().unwrap_or_else(|e| e.into_inner()).view(&b);
            ok(stream, JSON, json(&body), head_only).await
        }
        "/api/sensor" => {
            p.only(&["building", "sensor"])?;
            let (b, s) = (p.building()?, p.sensor()?);
            let body = sensor_detail(&ctx.session, ctx.fleet.provenance(), &b, &s).await;
            ok(stream, JSON, json(&body), head_only).await
        }
        "/api/history" => {
            p.only(&[
                "building",
                "sensor",
                "from_ns",
                "to_ns",
                "width",
                "calibration",
            ])?;
            let body = history(ctx, &p).await?;
            ok(stream, JSON, json(&body), head_only).await
        }
        "/api/helicorder" => {
            p.only(&["building", "sensor", "axis", "from_ns", "to_ns", "row_s"])?;
            let body = helicorder(ctx, &p).await?;
            ok(stream, JSON, json(&body), head_only).await
        }
        "/api/processed" => {
            p.only(&[
                "building", "sensor", "from_ns", "to_ns", "width", "quantity", "band",
            ])?;
            let body = processed(ctx, &p).await?;
            ok(stream, JSON, json(&body), head_only).await
        }
        "/api/trend" => {
            p.only(&["building", "sensor", "from_ns", "to_ns"])?;
            let body = trend(ctx, &p).await?;
            ok(stream, JSON, json(&body), head_only).await
        }
        "/api/spectrum" => {
            p.only(&["building", "sensor", "from_ns", "to_ns", "segment"])?;
            let body = spectrum(ctx, &p).await?;
            ok(stream, JSON, json(&body), head_only).await
        }
        "/api/spectrogram" => {
            p.only(&[
                "building", "sensor", "from_ns", "to_ns", "axis", "segment", "columns",
            ])?;
            let body = spectrogram(ctx, &p).await?;
            ok(stream, JSON, json(&body), head_only).await
        }
        "/api/export.mseed" => {
            p.only(&["building", "sensor", "from_ns", "to_ns", "network"])?;
            let (name, body) = export_mseed(ctx, &p).await?;
            let _ = http::respond_download(
                stream,
                "application/vnd.fdsn.mseed",
                &name,
                &body,
                head_only,
            )
            .await;
            Ok(())
        }
        "/api/export.csv" => {
            p.only(&["building", "sensor", "from_ns", "to_ns"])?;
            let (name, body) = export_csv(ctx, &p).await?;
            let _ = http::respond_download(
                stream,
                "text/csv; charset=utf-8",
                &name,
                body.as_bytes(),
                head_only,
            )
            .await;
            Ok(())
        }
        "/events" => {
            p.only(&["building", "sensor", "span_s", "width", "lite"])?;
            let sensor = match (p.get("building"), p.get("sensor")) {
                (None, None) => None,
                _ => Some((p.building()?, p.sensor()?)),
            };
            let span_s = p.int("span_s", Some(30), 1..=KEEP_NS / 1_000_000_000)?;
            let width = p.int("width", Some(1000), WIDTH_RANGE)?;
            let lite = p.int("lite", Some(0), 0..=1)? == 1;
            let Ok(permit) = ctx.streams.clone().try_acquire_owned() else {
                return Err(Refusal::new(
                    503,
                    format!(
                        "too many live streams open ({}); close a console tab",
                        ctx.options.max_streams
                    ),
                ));
            };
            if req.head_only {
                return ok(stream, "text/event-stream", Vec::new(), head_only).await;
            }
            events(ctx, stream, sensor, span_s * 1_000_000_000, width, lite).await;
            drop(permit);
            Ok(())
        }
        _ => Err(Refusal::new(404, format!("no such page: {:?}", req.path))),
    }
}

/// Most alerts one `/api/alerts` answer lists.
pub const MAX_ALERTS_LISTED: i64 = 1000;

fn alert_query(p: &Params<'_>) -> Result<AlertQuery, Refusal> {
    let bad = |name: &str, v: &str, what: &str| {
        Refusal::new(400, format!("parameter {name:?}: {v:?} is not {what}"))
    };
    let mut q = AlertQuery {
        limit: usize::try_from(p.int("limit", Some(200), 1..=MAX_ALERTS_LISTED)?).unwrap_or(200),
        ..AlertQuery::default()
    };
    if p.get("id").is_some() {
        q.id = Some(p.int("id", None, 1..=i64::MAX)? as u64);
    }
    if p.get("building").is_some() {
        q.building = Some(p.building()?);
    }
    if p.get("sensor").is_some() {
        q.sensor = Some(p.sensor()?);
    }
    if let Some(k) = p.get("kind") {
        q.kind = Some(
            serde_json::from_value(serde_json::Value::String(k.into())).map_err(|_| {
                bad(
                    "kind",
                    k,
                    "peak_acceleration, rms_acceleration, dominant_frequency, tilt_change or stale",
                )
            })?,
        );
    }
    if let Some(l) = p.get("level") {
        q.level = Some(match l {
            "exceeded" => LevelFilter::Verified(AlertLevel::Exceeded),
            "possible" => LevelFilter::Verified(AlertLevel::Possible),
            "stale" => LevelFilter::Verified(AlertLevel::Stale),
            "unverified" => LevelFilter::Unverified,
            _ => return Err(bad("level", l, "exceeded, possible, stale or unverified")),
        });
    }
    if let Some(st) = p.get("state") {
        q.state = match st {
            "all" => StateFilter::All,
            "open" => StateFilter::Open,
            "acknowledged" => StateFilter::Acknowledged,
            "silenced" => StateFilter::Silenced,
            _ => return Err(bad("state", st, "all, open, acknowledged or silenced")),
        };
    }
    if p.get("from_ns").is_some() {
        q.from_ns = Some(p.int("from_ns", None, 0..=i64::MAX)?);
    }
    if p.get("to_ns").is_some() {
        q.to_ns = Some(p.int("to_ns", None, 0..=i64::MAX)?);
    }
    Ok(q)
}

/// Checks a write's origin and content type, and reads its body: a JSON object.
fn check_write(req: &Request) -> Result<serde_json::Map<String, serde_json::Value>, Refusal> {
    if let Some(origin) = &req.origin {
        let own = req.host.as_deref().map(|h| format!("http://{h}"));
        if own
            .as_deref()
            .is_none_or(|o| !o.eq_ignore_ascii_case(origin))
        {
            return Err(Refusal::new(
                403,
                format!(
                    "Origin {origin:?} is not this console's ({}): writes are taken from the \
                     console's own page only",
                    own.unwrap_or_else(|| "no Host given".into())
                ),
            ));
        }
    }
    let json_type = req.content_type.as_deref().is_some_and(|t| {
        t.split(';')
            .next()
            .is_some_and(|m| m.trim().eq_ignore_ascii_case("application/json"))
    });
    if !json_type {
        return Err(Refusal::new(
            415,
            format!(
                "Content-Type {:?}: the body must be application/json",
                req.content_type.as_deref().unwrap_or("(none)")
            ),
        ));
    }
    let body: serde_json::Value = serde_json::from_slice(&req.body)
        .map_err(|e| Refusal::new(400, format!("the body is not JSON: {e}")))?;
    match body {
        serde_json::Value::Object(o) => Ok(o),
        _ => Err(Refusal::new(400, "the body must be a JSON object")),
    }
}

/// `POST /api/login`: a name and password checked against the accounts; a session cookie.
async fn login(
    ctx: &Context,
    stream: &mut TcpStream,
    body: &serde_json::Map<String, serde_json::Value>,
) -> Result<(), Refusal> {
    let b = Body(body);
    b.only(&["name", "password"])?;
    let (name, password) = (b.text("name", true)?, b.text("password", true)?);
    let Ok(_permit) = ctx.logins.clone().try_acquire_owned() else {
        return Err(Refusal::new(
            503,
            format!("{MAX_LOGINS_AT_ONCE} logins are being checked; try again in a moment"),
        ));
    };
    let ops = ctx.operators.clone();
    // An Argon2 check is CPU work: off the runtime's threads.
    let (n, pw) = (name.clone(), password);
    let outcome = tokio::task::spawn_blocking(move || ops.login(&n, &pw))
        .await
        .map_err(|e| Refusal::new(500, format!("login check failed: {e}")))?;
    match outcome {
        Login::Ok(token, who) => {
            tracing::info!(operator = %who.name, role = who.role.name(), "operator logged in");
            let body = json(&serde_json::json!({ "operator": who }));
            let _ = http::respond_setting_cookie(
                stream,
                "application/json",
                &body,
                &crate::operators::set_cookie(&token),
            )
            .await;
            Ok(())
        }
        Login::Refused => {
            tracing::warn!(operator = %name, "login refused");
            Err(Refusal::new(
                401,
                "login refused: no such operator, or a wrong password",
            ))
        }
    }
}

/// Applies a write by `who` (the role already checked).
fn write(
    ctx: &Context,
    req: &Request,
    obj: &serde_json::Map<String, serde_json::Value>,
    who: &Operator,
) -> Result<serde_json::Value, Refusal> {
    let b = Body(obj);
    let now = time::OffsetDateTime::now_utc();
    let field = |e: crate::alertlog::FieldError| Refusal::new(400, e.to_string());
    let by = who.name.clone();
    match req.path.as_str() {
        "/api/health/clear" => {
            b.only(&["building", "sensor", "reason"])?;
            Err(Refusal::new(
                501,
                "clearing a field-health latch is not available yet: the gateways do not offer \
                 it; a sensor's `calibration_suspect` ends when a new record is in force",
            ))
        }
        "/api/alerts/ack" => {
            b.only(&["ids", "note"])?;
            let ids = b.ids("ids")?;
            let note = b.text("note", false)?;
            let done = ctx
                .fleet
                .with_log(|l| l.acknowledge(&ids, &by, &note, now))
                .map_err(field)?;
            let already: Vec<u64> = ids.iter().copied().filter(|i| !done.contains(i)).collect();
            Ok(serde_json::json!({ "acknowledged": done, "already_acknowledged": already }))
        }
        "/api/alerts/silence" => {
            b.only(&["building", "sensor", "kind", "duration_s", "reason"])?;
            let building = BuildingId::new(b.text("building", true)?)
                .map_err(|e| Refusal::new(400, format!("field \"building\": {e}")))?;
            let sensor = match b.text("sensor", false)? {
                s if s.is_empty() => None,
                s => Some(
                    SensorId::new(s)
                        .map_err(|e| Refusal::new(400, format!("field \"sensor\": {e}")))?,
                ),
            };
            let kind = match b.text("kind", false)? {
                k if k.is_empty() => None,
                k => Some(
                    serde_json::from_value(serde_json::Value::String(k.clone())).map_err(|_| {
                        Refusal::new(
                            400,
                            format!(
                                "field \"kind\": {k:?} is not peak_acceleration, rms_acceleration, \
                                 dominant_frequency, tilt_change or stale"
                            ),
                        )
                    })?,
                ),
            };
            let duration_s = b.number("duration_s")?;
            let duration = Duration::try_from_secs_f64(duration_s).map_err(|_| {
                Refusal::new(
                    400,
                    format!("field \"duration_s\": {duration_s} is not a duration"),
                )
            })?;
            let reason = b.text("reason", false)?;
            let s = ctx
                .fleet
                .with_log(|l| l.silence(building, sensor, kind, duration, &by, &reason, now))
                .map_err(field)?;
            Ok(serde_json::to_value(s).unwrap_or_default())
        }
        "/api/alerts/lift" => {
            b.only(&["id"])?;
            let id = b.ids("id")?;
            let [id] = id[..] else {
                return Err(Refusal::new(400, "field \"id\": one silence id"));
            };
            let s = ctx
                .fleet
                .with_log(|l| l.lift(id, &by, now))
                .map_err(field)?;
            Ok(serde_json::to_value(s).unwrap_or_default())
        }
        "/api/annotations" => {
            b.only(&["building", "sensor", "from_ns", "to_ns", "text"])?;
            let building = BuildingId::new(b.text("building", true)?)
                .map_err(|e| Refusal::new(400, format!("field \"building\": {e}")))?;
            let sensor = match b.text("sensor", false)? {
                s if s.is_empty() => None,
                s => Some(
                    SensorId::new(s)
                        .map_err(|e| Refusal::new(400, format!("field \"sensor\": {e}")))?,
                ),
            };
            let (from_ns, to_ns) = (b.int("from_ns")?, b.int("to_ns")?);
            let text = b.text("text", true)?;
            let a = ctx
                .annotations
                .lock()
                .unwrap_or_else(|e| e.into_inner())
                .add(building, sensor, from_ns, to_ns, &text, &by, now)
                .map_err(field)?;
            Ok(serde_json::to_value(a).unwrap_or_default())
        }
        "/api/annotations/delete" => {
            b.only(&["id"])?;
            let id = b.ids("id")?;
            let [id] = id[..] else {
                return Err(Refusal::new(400, "field \"id\": one annotation id"));
            };
            let a = ctx
                .annotations
                .lock()
                .unwrap_or_else(|e| e.into_inner())
                .delete(id, &by, who.role >= Role::Admin, now)
                .map_err(field)?;
            Ok(serde_json::json!({ "deleted": a }))
        }
        other => Err(Refusal::new(404, format!("no such page: {other:?}"))),
    }
}

/// The fields of a write's JSON body.
struct Body<'a>(&'a serde_json::Map<String, serde_json::Value>);

impl Body<'_> {
    fn only(&self, known: &[&str]) -> Result<(), Refusal> {
        match self.0.keys().find(|k| !known.contains(&k.as_str())) {
            None => Ok(()),
            Some(k) => Err(Refusal::new(
                400,
                format!("unknown field {k:?} (known here: {})", known.join(", ")),
            )),
        }
    }

    /// A string field; absent or null reads as empty unless `required`.
    fn text(&self, name: &str, required: bool) -> Result<String, Refusal> {
        match self.0.get(name) {
            Some(serde_json::Value::String(s)) => Ok(s.clone()),
            None | Some(serde_json::Value::Null) if !required => Ok(String::new()),
            None | Some(serde_json::Value::Null) => {
                Err(Refusal::new(400, format!("field {name:?} is required")))
            }
            Some(v) => Err(Refusal::new(
                400,
                format!("field {name:?}: {v} is not a string"),
            )),
        }
    }

    /// A whole number (ns since the Unix epoch, for instance).
    fn int(&self, name: &str) -> Result<i64, Refusal> {
        match self.0.get(name) {
            Some(v) => v.as_i64().ok_or_else(|| {
                Refusal::new(400, format!("field {name:?}: {v} is not a whole number"))
            }),
            None => Err(Refusal::new(400, format!("field {name:?} is required"))),
        }
    }

    fn number(&self, name: &str) -> Result<f64, Refusal> {
        match self.0.get(name) {
            Some(v) => v
                .as_f64()
                .filter(|x| x.is_finite() && *x > 0.0)
                .ok_or_else(|| {
                    Refusal::new(400, format!("field {name:?}: {v} is not a positive number"))
                }),
            None => Err(Refusal::new(400, format!("field {name:?} is required"))),
        }
    }

    /// A whole number or an array of them.
    fn ids(&self, name: &str) -> Result<Vec<u64>, Refusal> {
        let bad = |v: &serde_json::Value| {
            Refusal::new(
                400,
                format!("field {name:?}: {v} is not an alert id or a list of them"),
            )
        };
        match self.0.get(name) {
            None => Err(Refusal::new(400, format!("field {name:?} is required"))),
            Some(v @ serde_json::Value::Array(items))
                if items.len() <= MAX_ALERTS_LISTED as usize =>
            {
                items
                    .iter()
                    .map(|i| i.as_u64().ok_or_else(|| bad(v)))
                    .collect()
            }
            Some(v) => v.as_u64().map(|i| vec![i]).ok_or_else(|| bad(v)),
        }
    }
}

fn json<T: serde::Serialize>(v: &T) -> Vec<u8> {
    // The console's own types serialise without failing: string keys, no foreign Serialize.
    serde_json::to_vec(v).unwrap_or_else(|e| {
        tracing::error!(cause = %e, "serialising a response failed");
        b"null".to_vec()
    })
}

/// The query parameters of one request.
struct Params<'a>(&'a [(String, String)]);

impl Params<'_> {
    fn get(&self, name: &str) -> Option<&str> {
        self.0
            .iter()
            .find(|(k, _)| k == name)
            .map(|(_, v)| v.as_str())
    }

    /// Refuses a parameter not in `known`, naming it.
    fn only(&self, known: &[&str]) -> Result<(), Refusal> {
        match self.0.iter().find(|(k, _)| !known.contains(&k.as_str())) {
            None => Ok(()),
            Some((k, _)) => Err(Refusal::new(
                400,
                format!(
                    "unknown parameter {k:?} (known here: {})",
                    if known.is_empty() {
                        "none".to_owned()
                    } else {
                        known.join(", ")
                    }
                ),
            )),
        }
    }

    fn required(&self, name: &str) -> Result<&str, Refusal> {
        self.get(name)
            .ok_or_else(|| Refusal::new(400, format!("parameter {name:?} is required")))
    }

    fn building(&self) -> Result<BuildingId, Refusal> {
        BuildingId::new(self.required("building")?)
            .map_err(|e| Refusal::new(400, format!("parameter \"building\": {e}")))
    }

    fn sensor(&self) -> Result<SensorId, Refusal> {
        SensorId::new(self.required("sensor")?)
            .map_err(|e| Refusal::new(400, format!("parameter \"sensor\": {e}")))
    }

    /// A whole number in `range`; `default` when absent (none: required).
    fn int(
        &self,
        name: &str,
        default: Option<i64>,
        range: std::ops::RangeInclusive<i64>,
    ) -> Result<i64, Refusal> {
        let v = match (self.get(name), default) {
            (None, Some(d)) => return Ok(d),
            (None, None) => self.required(name)?,
            (Some(v), _) => v,
        };
        let n: i64 = v.parse().map_err(|_| {
            Refusal::new(
                400,
                format!("parameter {name:?}: {v:?} is not a whole number"),
            )
        })?;
        if !range.contains(&n) {
            return Err(Refusal::new(
                400,
                format!(
                    "parameter {name:?}: {n} is outside {}..={}",
                    range.start(),
                    range.end()
                ),
            ));
        }
        Ok(n)
    }
}

/// The sensor's status and the record in force, as its gateway answers a one-sensor status
/// query; `error` says why there is none.
async fn sensor_detail(
    session: &zenoh::Session,
    provenance: &Provenance,
    b: &BuildingId,
    s: &SensorId,
) -> serde_json::Value {
    let key = Key::Status(b.clone()).to_string();
    let nonce = provenance.nonce();
    let selector = match &nonce {
        Some(n) => format!("{key}?sensor={s};nonce={n}"),
        None => format!("{key}?sensor={s}"),
    };
    let err = |m: String| serde_json::json!({ "building": b, "sensor_id": s, "error": m });
    let replies = match session
        .get(&selector)
        .consolidation(zenoh::query::ConsolidationMode::None)
        .timeout(Duration::from_secs(2))
        .await
    {
        Ok(r) => r,
        Err(e) => return err(format!("status query failed: {e}")),
    };
    // The first answer the gateway signed; any peer may answer too, and first.
    let mut refused = None;
    let status = loop {
        let Ok(reply) = replies.recv_async().await else {
            return err(match (refused, provenance.verifying()) {
                (Some(text), false) => format!("the gateway refused: {text}"),
                (Some(text), true) => {
                    format!("no verified answer from the gateway of building {b}; an unsigned refusal: {text}")
                }
                (None, false) => format!("no answer from the gateway of building {b}"),
                (None, true) => format!("no verified answer from the gateway of building {b}"),
            });
        };
        match reply.result() {
            Ok(sample) => {
                let payload = sample.payload().to_bytes();
                let attachment = sample.attachment().map(|a| a.to_bytes());
                let replied_on = sample.key_expr().as_str();
                if replied_on == key
                    && provenance.reply(
                        replied_on,
                        nonce.as_deref(),
                        &payload,
                        attachment.as_deref(),
                    )
                {
                    break from_json::<GatewayStatus>(&payload);
                }
            }
            Err(e) => {
                let text = String::from_utf8_lossy(&e.payload().to_bytes()).into_owned();
                // On trust, the first answer is the answer, as it always was.
                if !provenance.verifying() {
                    return err(format!("the gateway refused: {text}"));
                }
                refused = Some(text);
            }
        }
    };
    match status {
        Err(e) => err(format!("the gateway's answer does not decode: {e}")),
        Ok(st) => match st.sensors.into_iter().find(|x| &x.sensor_id == s) {
            None => err(format!(
                "the gateway of building {b} does not know sensor {s}"
            )),
            Some(sensor) => serde_json::json!({
                "building": b,
                "sensor_id": s,
                "gateway": st.gateway,
                "reported_at": st.reported_at.format(&time::format_description::well_known::Rfc3339).ok(),
                "history": st.history,
                "status": sensor,
            }),
        },
    }
}

/// A past range of one sensor, read from its gateway's history and decimated.
async fn history(ctx: &Context, p: &Params<'_>) -> Result<serde_json::Value, Refusal> {
    let (b, s) = (p.building()?, p.sensor()?);
    let from_ns = p.int("from_ns", None, 0..=i64::MAX)?;
    let to_ns = p.int("to_ns", None, 0..=i64::MAX)?;
    let width = p.int("width", Some(1000), WIDTH_RANGE)?;
    if to_ns <= from_ns || to_ns - from_ns > MAX_HISTORY_SPAN_NS {
        return Err(Refusal::new(
            400,
            format!(
                "parameters \"from_ns\", \"to_ns\": the range must be positive and at most {} s",
                MAX_HISTORY_SPAN_NS / 1_000_000_000
            ),
        ));
    }
    let calibration = match p.get("calibration") {
        None => None,
        Some(c @ ("in_force" | "latest")) => Some(c.to_owned()),
        Some(v) => match v.parse::<u64>() {
            Ok(n) if n >= 1 => Some(n.to_string()),
            _ => {
                return Err(Refusal::new(
                    400,
                    format!(
                        "parameter \"calibration\": {v:?} is not in_force, latest or a version ≥ 1"
                    ),
                ))
            }
        },
    };
    let bucket_ns = (to_ns - from_ns + width - 1) / width;
    let mut agg =
        Aggregator::new(from_ns, to_ns, bucket_ns).map_err(|e| Refusal::new(400, e.to_string()))?;
    let Ok(_permit) = ctx.history_queries.try_acquire() else {
        return Err(Refusal::new(
            503,
            format!(
                "{} history queries are running; try again in a moment",
                ctx.options.max_history_queries
            ),
        ));
    };
    let mut request = HistoryRequest::sensor(&b, &s);
    request.from_ns = Some(from_ns.saturating_sub(HISTORY_LEAD_NS));
    request.to_ns = Some(to_ns);
    request.calibration = calibration;
    request.trusted = ctx.fleet.provenance().keys().cloned();
    let fetched = triax_client::history::fetch(
        &ctx.session,
        &request,
        ctx.options.history_timeout,
        &mut |r| agg.push(&r.batch),
    )
    .await;
    let view = agg.finish();
    Ok(match fetched {
        // Zenoh answers a query nobody serves with nothing at all: say why it is empty.
        Ok(0) if ctx.fleet.gateway_state(&b) != GatewayState::Up => serde_json::json!({
            "source": "history",
            "batches_read": 0,
            "error": format!("no answer: the gateway of building {b} is not heard"),
            "view": view,
        }),
        Ok(n) => serde_json::json!({ "source": "history", "batches_read": n, "view": view }),
        Err(e) => serde_json::json!({ "source": "history", "error": e.to_string(), "view": view }),
    })
}

/// `from_ns` and `to_ns` of a request, checked: a positive range of at most `max_ns`.
fn range(p: &Params<'_>, max_ns: i64) -> Result<(i64, i64), Refusal> {
    let from_ns = p.int("from_ns", None, 0..=i64::MAX)?;
    let to_ns = p.int("to_ns", None, 0..=i64::MAX)?;
    if to_ns <= from_ns || to_ns - from_ns > max_ns {
        return Err(Refusal::new(
            400,
            format!(
                "parameters \"from_ns\", \"to_ns\": the range must be positive and at most {} s",
                max_ns / 1_000_000_000
            ),
        ));
    }
    Ok((from_ns, to_ns))
}

/// Reads a sensor's history over `[from_ns, to_ns)` (with [`HISTORY_LEAD_NS`] before it),
/// within the limit of history views at once. The error says why the read failed or came back
/// empty for want of a gateway.
async fn read_history(
    ctx: &Context,
    b: &BuildingId,
    s: &SensorId,
    from_ns: i64,
    to_ns: i64,
    each: &mut (dyn FnMut(&triax_protocol::batch::CorrectedBatch) + Send),
) -> Result<Result<usize, String>, Refusal> {
    let Ok(_permit) = ctx.history_queries.try_acquire() else {
        return Err(Refusal::new(
            503,
            format!(
                "{} history queries are running; try again in a moment",
                ctx.options.max_history_queries
            ),
        ));
    };
    let mut request = HistoryRequest::sensor(b, s);
    request.from_ns = Some(from_ns.saturating_sub(HISTORY_LEAD_NS));
    request.to_ns = Some(to_ns);
    request.trusted = ctx.fleet.provenance().keys().cloned();
    let fetched = triax_client::history::fetch(
        &ctx.session,
        &request,
        ctx.options.history_timeout,
        &mut |r| each(&r.batch),
    )
    .await;
    Ok(match fetched {
        Ok(0) if ctx.fleet.gateway_state(b) != GatewayState::Up => Err(format!(
            "no answer: the gateway of building {b} is not heard"
        )),
        Ok(n) => Ok(n),
        Err(e) => Err(e.to_string()),
    })
}

/// Per-minute aggregates over up to seven days: the minutes cached, the others read.
async fn trend(ctx: &Context, p: &Params<'_>) -> Result<serde_json::Value, Refusal> {
    let (b, s) = (p.building()?, p.sensor()?);
    let (from_ns, to_ns) = range(p, crate::trend::MAX_TREND_SPAN_NS)?;
    let (mut minutes, missing) = ctx.trends.lock().await.lookup(&b, &s, from_ns, to_ns);
    let mut read = 0;
    let mut error = None;
    // Minutes still filling are not kept, so that a trend read again completes them.
    let whole_before = crate::live::wall_clock_ns();
    for (from, to) in missing {
        let mut agg = crate::trend::TrendAggregator::new(from, to);
        match read_history(ctx, &b, &s, from, to, &mut |batch| agg.push(batch)).await? {
            Ok(n) => read += n,
            Err(e) => error = Some(e),
        }
        let got = agg.finish(whole_before);
        ctx.trends.lock().await.store(&b, &s, &got);
        minutes.extend(got);
        if error.is_some() {
            break;
        }
    }
    minutes.sort_by_key(|m| m.start_ns);
    Ok(serde_json::json!({
        "source": "trend",
        "from_ns": from_ns,
        "to_ns": to_ns,
        "minute_ns": crate::trend::MINUTE_NS,
        "batches_read": read,
        "error": error,
        "minutes": minutes,
    }))
}

/// Up to 24 h of one axis in rows, from the per-second store ([`crate::helicorder`]).
async fn helicorder(ctx: &Context, p: &Params<'_>) -> Result<serde_json::Value, Refusal> {
    use crate::helicorder::{SecondsBuilder, MAX_SPAN_NS, SECOND_NS};
    let (b, s) = (p.building()?, p.sensor()?);
    let (from_ns, to_ns) = range(p, MAX_SPAN_NS)?;
    let axis = match p.get("axis").unwrap_or("x") {
        "x" => 0,
        "y" => 1,
        "z" => 2,
        v => {
            return Err(Refusal::new(
                400,
                format!("parameter \"axis\": {v:?} is not x, y or z"),
            ))
        }
    };
    let row_s = p.int("row_s", Some(900), 60..=3600)?;
    let from_s = from_ns.div_euclid(SECOND_NS);
    let span_s = (to_ns - from_ns + SECOND_NS - 1) / SECOND_NS;
    let rows = ((span_s + row_s - 1) / row_s).max(1) as usize;
    let to_s = from_s + rows as i64 * row_s;
    let missing = ctx.helicorder.lock().await.missing(&b, &s, from_s, to_s);
    let whole_before_s = crate::live::wall_clock_ns() / SECOND_NS - 60;
    let mut read = 0;
    let mut error = None;
    for (a, z) in missing {
        // An hour at a time: each read is one history view, and the store fills as it goes.
        let mut at = a;
        while at < z && error.is_none() {
            let end = (at + 3600).min(z);
            let mut builder = SecondsBuilder::new(at * SECOND_NS, end * SECOND_NS);
            match read_history(ctx, &b, &s, at * SECOND_NS, end * SECOND_NS, &mut |batch| {
                builder.push(batch)
            })
            .await?
            {
                Ok(n) => {
                    read += n;
                    ctx.helicorder.lock().await.store(
                        &b,
                        &s,
                        at,
                        end,
                        whole_before_s,
                        builder.finish(),
                    );
                }
                Err(e) => error = Some(e),
            }
            at = end;
        }
    }
    let cache = ctx.helicorder.lock().await;
    let seconds = cache.get(&b, &s, from_s, to_s);
    let drum = crate::helicorder::drum(&seconds, axis, from_s, rows, row_s);
    Ok(serde_json::json!({
        "batches_read": read,
        "cached_seconds": cache.cached_seconds(),
        "error": error,
        "helicorder": drum,
    }))
}

/// A filtered or integrated view of up to an hour ([`crate::process`]).
async fn processed(ctx: &Context, p: &Params<'_>) -> Result<serde_json::Value, Refusal> {
    use crate::process::{Band, Quantity};
    let (b, s) = (p.building()?, p.sensor()?);
    let (from_ns, to_ns) = range(p, MAX_HISTORY_SPAN_NS)?;
    let width = p.int("width", Some(1000), WIDTH_RANGE)?;
    let v = p.get("quantity").unwrap_or("acceleration");
    let q = Quantity::parse(v).ok_or_else(|| {
        Refusal::new(
            400,
            format!("parameter \"quantity\": {v:?} is not acceleration, velocity or displacement"),
        )
    })?;
    let band = match p.get("band") {
        None => Band {
            low_hz: None,
            high_hz: None,
        },
        Some(v) => {
            Band::parse(v).map_err(|e| Refusal::new(400, format!("parameter \"band\": {e}")))?
        }
    };
    if q != Quantity::Acceleration && band.low_hz.is_none() {
        return Err(Refusal::new(
            400,
            "parameter \"band\": velocity and displacement need a lower edge (e.g. band=0.1-20): \
             an integral without one drifts without bound",
        ));
    }
    let settle = band.settle_ns();
    let mut c = crate::spectrum::Collector::new(from_ns - settle, to_ns + settle);
    let read = read_history(
        ctx,
        &b,
        &s,
        from_ns - settle,
        to_ns + settle,
        &mut |batch| c.push(batch),
    )
    .await?;
    let bucket_ns = (to_ns - from_ns + width - 1) / width;
    let view = crate::process::view(&c, q, band, from_ns, to_ns, bucket_ns);
    Ok(match read {
        Ok(n) => {
            serde_json::json!({ "batches_read": n, "settle_s": settle as f64 / 1e9, "view": view })
        }
        Err(e) => serde_json::json!({ "error": e, "settle_s": settle as f64 / 1e9, "view": view }),
    })
}

async fn spectrum(ctx: &Context, p: &Params<'_>) -> Result<serde_json::Value, Refusal> {
    let (b, s) = (p.building()?, p.sensor()?);
    let (from_ns, to_ns) = range(p, MAX_HISTORY_SPAN_NS)?;
    let segment = match p.get("segment") {
        None => None,
        Some(_) => Some(p.int(
            "segment",
            None,
            crate::spectrum::MIN_SEGMENT as i64..=crate::spectrum::MAX_SEGMENT as i64,
        )? as usize),
    };
    let mut c = crate::spectrum::Collector::new(from_ns, to_ns);
    let read = read_history(ctx, &b, &s, from_ns, to_ns, &mut |batch| c.push(batch)).await?;
    let answer = match (c.finish(segment), read) {
        (Ok(sp), Ok(n)) => serde_json::json!({ "batches_read": n, "spectrum": sp }),
        (Err(crate::spectrum::SpectrumError::Segment(n)), _) => {
            return Err(Refusal::new(
                400,
                format!(
                    "parameter \"segment\": {}",
                    crate::spectrum::SpectrumError::Segment(n)
                ),
            ))
        }
        (Ok(sp), Err(e)) => serde_json::json!({ "error": e, "spectrum": sp }),
        (Err(e), Ok(n)) => serde_json::json!({ "batches_read": n, "error": e.to_string() }),
        (Err(_), Err(e)) => serde_json::json!({ "error": e }),
    };
    Ok(answer)
}

async fn spectrogram(ctx: &Context, p: &Params<'_>) -> Result<serde_json::Value, Refusal> {
    use crate::spectrum::{SpectrumError, DEFAULT_COLUMNS, MAX_COLUMNS};
    let (b, s) = (p.building()?, p.sensor()?);
    let (from_ns, to_ns) = range(p, MAX_HISTORY_SPAN_NS)?;
    let axis = match p.get("axis").unwrap_or("x") {
        "x" => 0,
        "y" => 1,
        "z" => 2,
        v => {
            return Err(Refusal::new(
                400,
                format!("parameter \"axis\": {v:?} is not x, y or z"),
            ))
        }
    };
    let segment = match p.get("segment") {
        None => None,
        Some(_) => Some(p.int(
            "segment",
            None,
            crate::spectrum::MIN_SEGMENT as i64..=crate::spectrum::MAX_SPECTROGRAM_SEGMENT as i64,
        )? as usize),
    };
    let columns = p.int(
        "columns",
        Some(DEFAULT_COLUMNS as i64),
        10..=MAX_COLUMNS as i64,
    )? as usize;
    let mut c = crate::spectrum::Collector::new(from_ns, to_ns);
    let read = read_history(ctx, &b, &s, from_ns, to_ns, &mut |batch| c.push(batch)).await?;
    Ok(match (c.spectrogram(axis, segment, columns), read) {
        (Err(e @ SpectrumError::SpectrogramSegment(_)), _) => {
            return Err(Refusal::new(400, format!("parameter \"segment\": {e}")))
        }
        (Ok(g), Ok(n)) => serde_json::json!({ "batches_read": n, "spectrogram": g }),
        (Ok(g), Err(e)) => serde_json::json!({ "error": e, "spectrogram": g }),
        (Err(e), Ok(n)) => serde_json::json!({ "batches_read": n, "error": e.to_string() }),
        (Err(_), Err(e)) => serde_json::json!({ "error": e }),
    })
}

/// Every calibrated sample of up to an hour as miniSEED 2, written by the export's own code
/// ([`triax_client::mseed`]): the nine channels of the sensor (acceleration, standard
/// uncertainty, flags per axis) in one file of 512-byte records, the day files of an SDS tree
/// laid end to end (miniSEED readers take records in any order). The records are staged in a
/// temporary directory, since the writer makes an archive, and read back.
async fn export_mseed(ctx: &Context, p: &Params<'_>) -> Result<(String, Vec<u8>), Refusal> {
    use triax_client::mseed::SdsWriter;
    let (b, s) = (p.building()?, p.sensor()?);
    let (from_ns, to_ns) = range(p, MAX_HISTORY_SPAN_NS)?;
    let network = p.get("network").unwrap_or("XX");
    let internal = |what: &str, e: &dyn std::fmt::Display| {
        tracing::warn!(cause = %e, "miniSEED export: {what}");
        Refusal::new(500, format!("miniSEED export: {what}: {e}"))
    };
    let dir = tempfile::Builder::new()
        .prefix("triax-console-mseed-")
        .tempdir()
        .map_err(|e| internal("a temporary directory", &e))?;
    let mut writer = SdsWriter::new(dir.path(), network, Default::default())
        .map_err(|e| Refusal::new(400, format!("parameter \"network\": {e}")))?;
    let mut failed: Option<triax_client::mseed::MseedError> = None;
    let read = read_history(ctx, &b, &s, from_ns, to_ns, &mut |batch| {
        if failed.is_some() {
            return;
        }
        if let Some(within) = trimmed(batch, from_ns, to_ns) {
            if let Err(e) = writer.push(&within) {
                failed = Some(e);
            }
        }
    })
    .await?;
    if let Err(e) = read {
        return Err(Refusal::new(502, format!("history of {b}/{s}: {e}")));
    }
    if let Some(e) = failed {
        return Err(Refusal::new(
            422,
            format!("miniSEED export of {b}/{s}: {e}"),
        ));
    }
    let staged = writer.stage().map_err(|e| internal("staging", &e))?;
    let written = staged.commit().map_err(|e| internal("writing", &e))?;
    let mut body = Vec::new();
    for path in written.keys() {
        let bytes = std::fs::read(path).map_err(|e| internal("reading back", &e))?;
        body.extend_from_slice(&bytes);
    }
    Ok((format!("{b}_{s}_{from_ns}_{to_ns}.mseed"), body))
}

/// The samples of `batch` within `[from_ns, to_ns)`, as a batch starting at the first of
/// them, so that an export holds the view's samples and no others (the CSV's rule).
fn trimmed(
    batch: &triax_protocol::batch::CorrectedBatch,
    from_ns: i64,
    to_ns: i64,
) -> Option<triax_protocol::batch::CorrectedBatch> {
    let h = &batch.header;
    let period_ns = 1e9 / h.sample_rate_hz;
    let at = |i: usize| h.timestamp_ns.saturating_add((i as f64 * period_ns) as i64);
    let keep: Vec<usize> = (0..batch.samples.len())
        .filter(|&i| (from_ns..to_ns).contains(&at(i)))
        .collect();
    let (&first, &last) = (keep.first()?, keep.last()?);
    let mut out = batch.clone();
    out.samples = batch.samples[first..=last].to_vec();
    out.header.timestamp_ns = at(first);
    if first > 0 {
        // A gap or a duplicate is said on the batch's first sample, which is not in the range.
        out.batch_flags &= !triax_protocol::batch::flags::BATCH_ONLY;
    }
    Some(out)
}

fn mode_name(m: triax_protocol::batch::Mode) -> &'static str {
    use triax_protocol::batch::Mode;
    match m {
        Mode::None => "none",
        Mode::Static => "static",
        Mode::Dynamic => "dynamic",
        Mode::Split => "split",
    }
}

/// Every sample of up to an hour, one line each, and a file name for it.
async fn export_csv(ctx: &Context, p: &Params<'_>) -> Result<(String, String), Refusal> {
    use std::fmt::Write;
    let (b, s) = (p.building()?, p.sensor()?);
    let (from_ns, to_ns) = range(p, MAX_HISTORY_SPAN_NS)?;
    let mut out = String::from(
        "time_utc,t_ns,sequence,ax_mps2,ay_mps2,az_mps2,ux_mps2,uy_mps2,uz_mps2,k,flags,calibration_version,mode\n",
    );
    let fmt = time::format_description::well_known::Rfc3339;
    let read = read_history(ctx, &b, &s, from_ns, to_ns, &mut |batch| {
        let h = &batch.header;
        let period_ns = 1e9 / h.sample_rate_hz;
        for (i, x) in batch.samples.iter().enumerate() {
            let t = h.timestamp_ns.saturating_add((i as f64 * period_ns) as i64);
            if t < from_ns || t >= to_ns {
                continue;
            }
            let utc = time::OffsetDateTime::from_unix_timestamp_nanos(i128::from(t))
                .ok()
                .and_then(|d| d.format(&fmt).ok())
                .unwrap_or_default();
            let [ax, ay, az] = x.accel_mps2;
            let [ux, uy, uz] = x.uncertainty_mps2;
            // Writing to a String cannot fail.
            let _ = writeln!(
                out,
                "{utc},{t},{},{ax},{ay},{az},{ux},{uy},{uz},{},{},{},{}",
                h.sequence,
                batch.info.coverage_factor,
                x.flags | batch.batch_flags,
                batch.info.calibration_version,
                mode_name(batch.info.mode),
            );
        }
    })
    .await?;
    if let Err(e) = read {
        return Err(Refusal::new(502, format!("history of {b}/{s}: {e}")));
    }
    Ok((format!("{b}_{s}_{from_ns}_{to_ns}.csv"), out))
}

/// The event stream of one page: the fleet (its brief, then its deltas every second) and, for a sensor view, its live frames
/// and tilt. Ends when the page goes, a write stalls, or the console stops.
///
/// A light stream (`lite`, for slow links) sends a live frame once a second holding only the
/// buckets that changed (from the bucket of the earliest batch that arrived since the last
/// frame, a late one included), and the fleet's deltas every 5 s: the page draws the same buckets,
/// later.
async fn events(
    ctx: &Context,
    stream: &mut TcpStream,
    sensor: Option<(BuildingId, SensorId)>,
    span_ns: i64,
    width: i64,
    lite: bool,
) {
    if http::start_events(stream).await.is_err() {
        return;
    }
    let mut stop = ctx.stop.clone();
    // The whole fleet first (its brief: states, not counters), then what changes.
    let (mut fleet_seq, first, mut fleet) = ctx.fleet_events.start(&ctx.fleet);
    if http::send_event(stream, "fleet", &first).await.is_err() {
        return;
    }
    let feed = match &sensor {
        None => None,
        Some((b, s)) => match ctx.feeds.open(b, s).await {
            Ok(f) => Some(f),
            Err(e) => {
                let msg = serde_json::json!({ "error": format!("cannot subscribe: {e}") });
                let _ = http::send_event(stream, "problem", &msg.to_string()).await;
                return;
            }
        },
    };
    let bucket_ns = (span_ns / width).max(1);
    let mut last_end: Option<i64> = None;
    let mut prepends = 0;
    let mut arrivals = 0;
    let mut last_tilt_ns = i64::MIN;
    let mut tick = tokio::time::interval(if lite { LITE_PERIOD } else { LIVE_PERIOD });
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
    let mut fleet_sent = tokio::time::Instant::now();
    loop {
        tokio::select! {
            _ = stop.changed() => return,
            changed = fleet.changed() => {
                if changed.is_err() {
                    return;
                }
                fleet.mark_unchanged();
                if lite && fleet_sent.elapsed() < LITE_FLEET_PERIOD {
                    // The deltas wait; the first one after the period sends them all.
                    continue;
                }
                fleet_sent = tokio::time::Instant::now();
                match ctx.fleet_events.since(fleet_seq) {
                    Some(deltas) => {
                        for (seq, text) in deltas {
                            if http::send_event(stream, "fleet_delta", &text).await.is_err() {
                                return;
                            }
                            fleet_seq = seq;
                        }
                    }
                    None => {
                        // Too far behind: the whole fleet again.
                        let (seq, text, _) = ctx.fleet_events.start(&ctx.fleet);
                        if http::send_event(stream, "fleet", &text).await.is_err() {
                            return;
                        }
                        fleet_seq = seq;
                    }
                }
            }
            _ = tick.tick() => {
                let Some(feed) = &feed else { continue };
                if feed.prepends() != prepends {
                    // The recent past arrived from the history: send the whole window again.
                    prepends = feed.prepends();
                    last_end = None;
                }
                let resend = if lite {
                    let (now, earliest) = feed.arrivals_since(arrivals);
                    if now == arrivals && last_end.is_some() {
                        continue;
                    }
                    arrivals = now;
                    Resend::From(earliest)
                } else {
                    Resend::Last(RESEND_NS)
                };
                if let Some(frame) = live_frame(feed, &mut last_end, span_ns, bucket_ns, resend) {
                    if http::send_event(stream, "live", &frame).await.is_err() {
                        return;
                    }
                }
                let tilt = feed.tilt_after(last_tilt_ns);
                if let Some(t) = tilt.last() {
                    last_tilt_ns = t.timestamp_ns;
                    let text = serde_json::to_string(&tilt).unwrap_or_default();
                    if http::send_event(stream, "tilt", &text).await.is_err() {
                        return;
                    }
                }
            }
        }
    }
}

/// What a live frame repeats of what it sent before.
#[derive(Debug, Clone, Copy)]
enum Resend {
    /// This much before the end of the last frame.
    Last(i64),
    /// From this time (the earliest batch that arrived since), if any arrived.
    From(Option<i64>),
}

/// The next live frame, if the stream moved: the whole window the first time, then what is new
/// and what `resend` says (the page replaces buckets by index, so a frame starts on a bucket's
/// start: a bucket sent in part would replace the whole one).
fn live_frame(
    feed: &crate::live::Feed,
    last_end: &mut Option<i64>,
    span_ns: i64,
    bucket_ns: i64,
    resend: Resend,
) -> Option<String> {
    let newest = feed.newest_end_ns()?;
    if *last_end == Some(newest) && matches!(resend, Resend::Last(_) | Resend::From(None)) {
        return None;
    }
    let window_start = newest.saturating_sub(span_ns);
    let mut from = match (*last_end, resend) {
        (None, _) => window_start,
        (Some(e), Resend::Last(back)) => window_start.max(e.saturating_sub(back)),
        (Some(e), Resend::From(t)) => window_start.max(t.map_or(e, |t| t.min(e))),
    };
    if from >= newest {
        // The node's clock went back: start over.
        from = window_start;
    }
    // Keep within the bucket budget whatever the span and width.
    from = from.max(newest.saturating_sub(bucket_ns.saturating_mul(MAX_BUCKETS as i64 - 3)));
    from = from.div_euclid(bucket_ns) * bucket_ns;
    let view: View = feed.view(from, newest, bucket_ns).ok()?;
    *last_end = Some(newest);
    let frame = serde_json::json!({
        "building": feed.building,
        "sensor_id": feed.sensor,
        "span_ns": span_ns,
        "malformed": feed.malformed(),
        "view": view,
    });
    Some(frame.to_string())
}
