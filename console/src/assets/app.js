// Triax console, the page: views chosen by the URL fragment (#/ fleet, #/alerts,
// #/sensor/<building>/<sensor>[?at=<ns>&span=<s>], #/building/<building>, #/modes/<building>), fed by one Server-Sent Events stream and a
// few JSON requests to the console's own server. Plots are plain canvas over data the server
// has already decimated (one bucket per pixel column).
//
// Every string from the network is put into the page as text (textContent / text nodes), never
// as HTML: alert statements, lab names and certificate text are free text. The server's
// Content-Security-Policy forbids inline scripts as a second line of defence.
'use strict';
(() => {
  const FLAGS = [
    ['uncalibrated', '#b42318'], ['calibration_expired', '#d92d20'], ['outside_amplitude', '#dc6803'],
    ['outside_frequency', '#9e77ed'], ['sequence_gap', '#475467'], ['non_finite_input', '#000000'],
    ['clipped', '#f04438'], ['duplicate', '#0ba5ec'], ['outside_temperature', '#c11574'],
    ['calibration_suspect', '#7a2e0e'],
  ];
  const AXES = ['x', 'y', 'z'];
  const AXIS_COLORS = ['#175cd3', '#1d7a3a', '#9a3412'];
  const SPANS_S = [10, 30, 120, 600, 3600];
  const LIVE_MAX_SPAN_S = 600;
  const HISTORY_MAX_SPAN_S = 3600;

  // ---- DOM helpers: text only -------------------------------------------------------------
  function el(tag, attrs, ...children) {
    const e = document.createElement(tag);
    for (const [k, v] of Object.entries(attrs || {})) {
      if (v === undefined || v === null || v === false) continue;
      if (k === 'class') e.className = v;
      else if (k === 'text') e.textContent = String(v);
      else if (k === 'onclick' || k === 'onchange') e.addEventListener(k.slice(2), v);
      else e.setAttribute(k, String(v));
    }
    for (const c of children.flat(Infinity)) {
      if (c === undefined || c === null || c === false) continue;
      e.append(c instanceof Node ? c : document.createTextNode(String(c)));
    }
    return e;
  }
  const $ = (id) => document.getElementById(id);
  // ---- Times: UTC, the site's local time or this browser's, always labelled ----------------
  let tzMode = localStorage.getItem('triax.tz') || 'utc';   // 'utc' | 'site' | 'browser'
  let siteZone = null;                                        // the console's --time-zone
  const browserZone = () => Intl.DateTimeFormat().resolvedOptions().timeZone || 'UTC';
  const zoneName = () => tzMode === 'site' && siteZone ? siteZone : tzMode === 'browser' ? browserZone() : 'UTC';
  const zoneFormats = new Map();
  const pad2 = (n) => String(n).padStart(2, '0');
  // The wall clock at `ms` in the zone shown, and the zone's abbreviation there.
  function wall(ms) {
    const z = zoneName();
    if (z === 'UTC') { const d = new Date(ms); return { y: d.getUTCFullYear(), mo: d.getUTCMonth() + 1, d: d.getUTCDate(), h: d.getUTCHours(), mi: d.getUTCMinutes(), s: d.getUTCSeconds(), ms: d.getUTCMilliseconds(), abbr: 'UTC' }; }
    let f = zoneFormats.get(z);
    if (!f) { f = new Intl.DateTimeFormat('en-GB', { timeZone: z, hourCycle: 'h23', year: 'numeric', month: '2-digit', day: '2-digit', hour: '2-digit', minute: '2-digit', second: '2-digit', timeZoneName: 'short' }); zoneFormats.set(z, f); }
    const o = {};
    for (const p of f.formatToParts(new Date(ms))) o[p.type] = p.value;
    return { y: +o.year, mo: +o.month, d: +o.day, h: +o.hour % 24, mi: +o.minute, s: +o.second, ms: ((Math.floor(ms) % 1000) + 1000) % 1000, abbr: o.timeZoneName || z };
  }
  const wallDate = (w) => `${w.y}-${pad2(w.mo)}-${pad2(w.d)}`;
  const wallClock = (w) => `${pad2(w.h)}:${pad2(w.mi)}:${pad2(w.s)}`;
  // UTC keeps its ISO form (…Z); a local time says its zone (2027-01-15 09:00:00 CET).
  const fmtTime = (ms) => { if (!Number.isFinite(ms)) return '—'; const w = wall(ms); return `${wallDate(w)} ${wallClock(w)}` + (w.abbr === 'UTC' ? 'Z' : ` ${w.abbr}`); };
  // An axis label: the clock, with milliseconds when the ticks are finer than a second.
  const fmtTick = (ms, fine) => { const w = wall(ms); return fine ? `${pad2(w.mi)}:${pad2(w.s)}.${String(w.ms).padStart(3, '0')}` : wallClock(w); };
  const zoneLabel = () => zoneName() === 'UTC' ? 'UTC' : wall(Date.now()).abbr;
  // Wall-clock fields in the zone shown to an instant; null if that wall time does not exist
  // there (a spring-forward gap) or the fields do not make a date.
  function wallToMs(y, mo, d, h, mi, se) {
    const asUtc = Date.UTC(y, mo - 1, d, h, mi, se);
    if (zoneName() === 'UTC') return asUtc;
    const offset = (t) => { const w = wall(t); return Date.UTC(w.y, w.mo - 1, w.d, w.h, w.mi, w.s) - Math.floor(t / 1000) * 1000; };
    let t = asUtc - offset(asUtc);
    t = asUtc - offset(t);
    return t;
  }
  const fmtAge = (s) => s === null || s === undefined ? '—' : s < 1 ? 'now' : s < 120 ? `${s.toFixed(0)} s ago` : s < 7200 ? `${(s / 60).toFixed(0)} min ago` : `${(s / 3600).toFixed(1)} h ago`;
  const fmtNum = (x, d = 4) => x === null || x === undefined || !Number.isFinite(x) ? '—' : Number(x).toPrecision(d);
  // A coverage factor to three significant digits, without trailing zeros (2, 1.97).
  const fmtK = (k) => Number.isFinite(k) ? String(Number(Number(k).toPrecision(3))) : '?';
  // Units as the page writes them everywhere (the alerting service sends `m/s^2`).
  const fmtUnit = (u) => String(u ?? '').replace(/\^2/g, '²').replace(/\^3/g, '³');
  const fmtSpan = (s) => s >= 120 && s % 60 === 0 ? `${s / 60} min` : `${s} s`;
  const fmtShare = (f) => !f ? '—' : `${(100 * f.share).toFixed(f.share > 0 && f.share < 0.01 ? 1 : 0)} %`;
  // The time input reads and writes ISO 8601 in the zone shown, as every other time on the page.
  const fmtInput = (ms) => { const w = wall(ms); return `${wallDate(w)} ${wallClock(w)}`; };
  const parseInput = (text) => {
    const m = /^\s*(\d{4})-(\d{2})-(\d{2})[ T](\d{2}):(\d{2})(?::(\d{2}))?Z?\s*$/.exec(text);
    if (!m) return null;
    const [y, mo, d, h, mi, se] = m.slice(1).map((x) => Number(x || 0));
    const ms = wallToMs(y, mo, d, h, mi, se);
    // Date.UTC rolls 2027-02-30 over to March: refuse what does not read back the same.
    return fmtInput(ms) === `${m[1]}-${m[2]}-${m[3]} ${m[4]}:${m[5]}:${m[6] || '00'}` ? ms : null;
  };
  const fmtBytes = (b) => b >= 1 << 30 ? `${(b / (1 << 30)).toFixed(2)} GiB` : b >= 1 << 20 ? `${(b / (1 << 20)).toFixed(1)} MiB` : `${(b / 1024).toFixed(0)} KiB`;
  const nsToMs = (ns) => ns / 1e6;
  const msToNs = (ms) => (BigInt(Math.round(ms)) * 1000000n).toString();
  const sensorHref = (b, s, atNs, spanS) => `#/sensor/${encodeURIComponent(b)}/${encodeURIComponent(s)}` +
    (atNs !== undefined ? `?at=${atNs}&span=${spanS || 60}` : '');
  const badge = (cls, text, title) => el('span', { class: `badge ${cls}`, title }, text ?? cls.replace(/_/g, ' '));
  const flagNames = (bits) => FLAGS.filter((_, i) => bits & (1 << i)).map(([n]) => n);
  // An alert is a verdict only when a trusted alerting key signed it (PROTOCOL.md §3.6); any
  // other is shown for what it is, with what it claims, never with the verdict's badge.
  const TRUST = {
    unsigned: 'not signed: anyone on the network can put such an alert',
    unknown_key: 'signed by a key this console was not given (--trusted-alert-key)',
    bad_signature: 'its signature does not verify: altered, or signed by another key',
  };
  const verified = (a) => a.trust === 'verified';
  const verdict = (a) => verified(a) ? badge(a.level)
    : badge('unverified', `unverified (claims ${a.level})`, `${a.trust.replace(/_/g, ' ')}: ${TRUST[a.trust] || ''}. Not a verdict.`);

  // ---- State ------------------------------------------------------------------------------
  let fleet = null;          // last fleet snapshot
  let route = null;          // current route
  let source = null;         // EventSource
  let live = null;           // live data of the sensor view
  let tilt = [];             // tilt samples of the sensor view
  let historyView = null;    // history data of the sensor view
  let detail = null;         // /api/sensor answer
  let trendView = null;      // /api/trend answer of the sensor view
  let spectrumView = null;   // /api/spectrum answer
  let spectrogramView = null; // /api/spectrogram answer
  let alertInfo = null;      // the alert a link came from
  let drawPending = false;

  function parseRoute() {
    let h;
    try { h = decodeURI(location.hash || '#/'); } catch (e) { h = '#/'; }
    const [path, query] = h.slice(1).split('?');
    const params = new URLSearchParams(query || '');
    const parts = path.split('/').filter(Boolean);
    if (parts[0] === 'alerts') return { view: 'alerts', params };
    if (parts[0] === 'modes' && parts.length === 2) return { view: 'modes', building: parts[1] };
    if (parts[0] === 'helicorder' && (parts.length === 2 || parts.length === 3)) {
      const num = (k, d, ok) => { const v = Number(params.get(k)); return params.get(k) !== null && ok(v) ? v : d; };
      const r = { view: 'helicorder', building: parts[1], sensor: parts[2] || null, axis: AXES.includes(params.get('axis')) ? params.get('axis') : 'x',
        hours: num('hours', 24, (v) => [1, 2, 6, 12, 24].includes(v)), row: num('row', 900, (v) => [300, 600, 900, 1800, 3600].includes(v)),
        end: num('end', null, (v) => Number.isFinite(v) && v > 0) };
      const endMs = r.end === null ? Date.now() : r.end / 1e6;
      r.window = [endMs - r.hours * 3600e3, endMs];
      return r;
    }
    if (parts[0] === 'building' && parts.length === 2) {
      const r = { view: 'building', building: parts[1], error: null, axis: ['x', 'y', 'z'].includes(params.get('axis')) ? params.get('axis') : 'x', alert: /^\d+$/.test(params.get('alert') || '') ? Number(params.get('alert')) : null,
        overlay: (params.get('overlay') || '').split('').filter((a, i, all) => AXES.includes(a) && all.indexOf(a) === i).join('') };
      processingParams(params, r);
      const at = params.get('at');
      if (at !== null && /^\d{1,19}$/.test(at)) { r.at = Number(at); r.span = Math.min(HISTORY_MAX_SPAN_S, Math.max(1, Number(params.get('span')) || 60)); }
      const w = windowParams(params, r);
      r.window = w || [Date.now() - 600000, Date.now()];
      return r;
    }
    if (parts[0] === 'sensor' && parts.length === 3) {
      // A link is typed, pasted and edited by people: say what is wrong with it rather than
      // throw, and never keep showing the previous view as if it were the one asked for.
      const r = { view: 'sensor', building: parts[1], sensor: parts[2], at: null, span: 30, error: null };
      const at = params.get('at'), span = params.get('span');
      if (span !== null) {
        if (/^\d{1,4}$/.test(span) && Number(span) >= 1 && Number(span) <= HISTORY_MAX_SPAN_S) r.span = Number(span);
        else r.error = `span=${span} is not a whole number of seconds from 1 to ${HISTORY_MAX_SPAN_S}`;
      }
      if (at !== null) {
        const ms = /^\d{1,19}$/.test(at) ? Number(at) / 1e6 : NaN;
        if (!Number.isFinite(new Date(ms).getTime())) r.error = `at=${at} is not a time in nanoseconds since 1970-01-01 UTC`;
        else if (ms - 0.75 * r.span * 1000 > Date.now()) r.error = `at=${at} (${fmtTime(ms)}) is in the future`;
        else r.at = Number(at);
      }
      r.alert = /^\d+$/.test(params.get('alert') || '') ? Number(params.get('alert')) : null;
      processingParams(params, r);
      r.window = r.error ? null : windowParams(params, r);
      if (r.window && r.at === null) r.at = msToNs(r.window[1] - 0.25 * (r.window[1] - r.window[0]));
      return r;
    }
    return { view: 'fleet' };
  }

  // What a plot shows: acceleration as corrected, or band-passed, or integrated to velocity or
  // displacement within a band (`q`, `band` in the link; /api/processed).
  const QUANTITIES = { acceleration: 'm/s²', velocity: 'm/s', displacement: 'm' };
  function processingParams(params, r) {
    const q = params.get('q');
    r.quantity = QUANTITIES[q] ? q : 'acceleration';
    const band = params.get('band') || '';
    r.band = /^[0-9.]*-[0-9.]*$/.test(band) && band !== '-' ? band : '';
    if (r.quantity !== 'acceleration' && !r.band) r.band = '0.1-';
  }
  const processing = (r) => r.quantity !== 'acceleration' || !!r.band;
  // The link's processing, to keep across zoom, pan and steps.
  const processingExtra = (r = route) => (r.quantity && r.quantity !== 'acceleration' ? `&q=${r.quantity}` : '') + (r.band ? `&band=${encodeURIComponent(r.band)}` : '') + (r.overlay ? `&overlay=${r.overlay}` : '');

  // The window a link names: `from`/`to` (ns), `last` (seconds up to now), or `at`/`span`;
  // null for live. Up to 7 days; beyond an hour the view is a trend of per-minute aggregates.
  const TREND_MAX_S = 7 * 86400;
  function windowParams(params, r) {
    const from = params.get('from'), to = params.get('to'), last = params.get('last'), at = params.get('at');
    if (from !== null || to !== null) {
      if (!/^\d{1,19}$/.test(from || '') || !/^\d{1,19}$/.test(to || '') || Number(to) <= Number(from) || (Number(to) - Number(from)) / 1e9 > TREND_MAX_S) {
        r.error = `from=${from} and to=${to} are not a range of up to 7 days in nanoseconds since 1970-01-01 UTC`;
        return null;
      }
      return [Number(from) / 1e6, Math.min(Number(to) / 1e6, Date.now())];
    }
    if (last !== null) {
      if (!/^\d{1,6}$/.test(last) || Number(last) < 1 || Number(last) > TREND_MAX_S) { r.error = `last=${last} is not a whole number of seconds from 1 to ${TREND_MAX_S}`; return null; }
      r.last = Number(last);
      return [Date.now() - Number(last) * 1000, Date.now()];
    }
    if (at !== null && r.at !== null && r.at !== undefined) { r.atGiven = true; return windowOf(r.at, r.span); }
    return null;
  }

  // ---- Live connection --------------------------------------------------------------------
  function setConn(state, text) { $('conn').dataset.state = state; $('conn').textContent = text; }

  function connect(query) {
    if (source) source.close();
    clearTimeout(retryTimer);
    const url = '/events' + (query ? '?' + query : '');
    const me = new EventSource(url);
    source = me;
    setConn('connecting', 'connecting…');
    me.onopen = () => setConn('open', 'live');
    me.onerror = () => {
      if (source !== me) return;
      // The browser retries by itself after a network error; after an HTTP answer other than
      // the stream (a 400, a 503) it gives up: ask what the console said.
      if (me.readyState === EventSource.CLOSED) explainRefusal(me, url, query);
      else setConn('reconnecting', 'console unreachable, retrying…');
    };
    me.addEventListener('fleet', (e) => { const f = JSON.parse(e.data); if (f) onFleetWhole(f); });
    me.addEventListener('fleet_delta', (e) => onFleetDelta(JSON.parse(e.data), query));
    source.addEventListener('live', (e) => onLive(JSON.parse(e.data)));
    source.addEventListener('tilt', (e) => onTilt(JSON.parse(e.data)));
    source.addEventListener('problem', (e) => { const p = $('status-line'); if (p) p.textContent = JSON.parse(e.data).error; });
  }

  let retryTimer = null;
  async function explainRefusal(me, url, query) {
    const abort = new AbortController();
    let status = 0, text = '';
    try {
      const resp = await fetch(url, { signal: abort.signal });
      status = resp.status;
      if (resp.ok) abort.abort(); else text = (await resp.text()).trim();
    } catch (e) { /* unreachable after all */ }
    if (source !== me) return;
    if (status === 0 || status === 200) {
      setConn('reconnecting', 'console unreachable, retrying…');
      retryTimer = setTimeout(() => connect(query), 2000);
    } else if (status === 503) {
      setConn('refused', `console busy (${status}): ${text}; retrying in 5 s`);
      retryTimer = setTimeout(() => connect(query), 5000);
    } else {
      setConn('refused', `console refused (${status}): ${text}`);
    }
  }

  // What a request to the console answered, or why there was no answer, as `{ error }`.
  async function getJson(path) {
    let resp;
    try { resp = await fetch(path); } catch (e) { return { error: `console unreachable (${e.message || e})` }; }
    if (!resp.ok) return { error: `console refused (${resp.status}): ${(await resp.text()).trim()}` };
    return resp.json();
  }

  // ---- The fleet: its brief from the event stream, the counters on demand -------------------
  // The `fleet` event carries per building and sensor what changes seldom (states, calibration,
  // the latest alert's id); `fleet_delta` what changed since, once a second. The counters that
  // move with every status answer (samples, last seen, flagged share) are read for the
  // buildings shown, from /api/fleet?building=, every 2 s.
  let fleetSeq = null;
  const alertById = new Map();
  const rows = new Map();    // building → its /api/fleet?building= answer
  const expanded = new Set();
  const remember = (list) => { for (const a of list || []) alertById.set(a.id, a); while (alertById.size > 2000) alertById.delete(alertById.keys().next().value); };

  function onFleetWhole(f) {
    fleet = f; fleetSeq = f.seq;
    fleet.refused_messages = Object.values((f.provenance && f.provenance.refused) || {}).reduce((x, y) => x + y, 0);
    remember(f.alerts);
    onFleet(true);
  }

  function onFleetDelta(d, query) {
    if (!fleet) return;
    if (d.seq !== fleetSeq + 1) { connect(query); return; }   // one missed: start again whole
    fleetSeq = d.seq;
    for (const k of ['now', 'alerts_total', 'alerts_open', 'malformed_messages', 'ignored_buildings', 'refused_messages']) fleet[k] = d[k];
    const building = (id) => fleet.buildings.find((b) => b.building === id);
    for (const b of d.buildings || []) {
      const x = building(b.building);
      if (x) Object.assign(x, b); else fleet.buildings.push({ ...b, sensors: [] });
    }
    if (d.removed_buildings) fleet.buildings = fleet.buildings.filter((b) => !d.removed_buildings.includes(b.building));
    fleet.buildings.sort((a, b) => a.building < b.building ? -1 : 1);
    const touched = new Set();
    for (const s of d.sensors || []) {
      const b = building(s.building);
      if (!b) continue;
      const { building: _, ...brief } = s;
      const i = b.sensors.findIndex((x) => x.sensor_id === s.sensor_id);
      if (i >= 0) b.sensors[i] = brief; else b.sensors.push(brief);
      touched.add(b);
    }
    for (const [bid, sid] of d.removed_sensors || []) { const b = building(bid); if (b) { b.sensors = b.sensors.filter((x) => x.sensor_id !== sid); touched.add(b); } }
    for (const b of touched) b.sensors.sort((a, c) => a.sensor_id < c.sensor_id ? -1 : 1);
    if (d.alerts) {
      remember(d.alerts);
      const ids = new Set(d.alerts.map((a) => a.id));
      fleet.alerts = [...d.alerts, ...fleet.alerts.filter((a) => !ids.has(a.id))].slice(0, 100);
    }
    const changed = !!(d.buildings || d.sensors || d.removed_sensors || d.removed_buildings || d.alerts);
    $('view').dataset.fleetDeltas = String(Number($('view').dataset.fleetDeltas || 0) + 1);
    onFleet(changed);
  }

  // A sensor's row: its brief, and its building's counters where they have been read.
  function sensorOf(b, s) {
    const r = rows.get(b.building);
    const c = r && r.sensors.find((x) => x.sensor_id === s.sensor_id);
    const latest = s.latest_alert === null || s.latest_alert === undefined ? null
      : (c && c.latest_alert && c.latest_alert.id === s.latest_alert ? c.latest_alert : alertById.get(s.latest_alert) || { id: s.latest_alert, missing: true });
    const expires = s.valid_until ? (Date.parse(s.valid_until) - Date.parse(fleet.now)) / 86400000 : null;
    return { flagged_share: null, last_seen: null, last_seen_age_s: null, samples: '…', gaps: 0, missing_batches: 0, rejects: '…', ...(c || {}), ...s, latest_alert: latest, expires_in_days: expires };
  }
  const buildingOf = (b) => ({ last_heard_s: null, malformed: null, dropped: null, history: null, ...(rows.get(b.building) || {}), ...b });

  // Buildings whose sensors are listed: all of a small fleet, else those opened.
  const isExpanded = (b) => fleet.buildings.length <= 3 || expanded.has(b.building);

  let rowsFetching = false;
  async function refreshRows() {
    if (!fleet || !route || rowsFetching) return;
    let wanted = [];
    if (route.view === 'fleet') wanted = fleet.buildings.filter(isExpanded).map((b) => [b.building, null]);
    else if (route.view === 'sensor') wanted = [[route.building, route.sensor]];
    if (!wanted.length) return;
    rowsFetching = true;
    const myRoute = route;
    for (const [b, sensor] of wanted) {
      const q = new URLSearchParams({ building: b });
      if (sensor) q.set('sensor', sensor);
      const body = await getJson('/api/fleet?' + q);
      if (!body.error) rows.set(b, body);
    }
    rowsFetching = false;
    if (route !== myRoute) return;
    if (route.view === 'fleet') renderFleet(); else if (route.view === 'sensor') renderSensorHeader();
  }
  setInterval(refreshRows, 2000);

  function onFleet(changed) {
    $('clock').textContent = fmtTime(Date.parse(fleet.now));
    $('alert-count').textContent = fleet.alerts_open ? `(${fleet.alerts_open} open)` : '';
    if (route.view === 'fleet') { if (changed) renderFleet(); if (changed && !rows.size) refreshRows(); }
    else if (route.view === 'alerts') refreshAlerts();
    else if (route.view === 'sensor' && changed) renderSensorHeader();
    else if (route.view === 'helicorder' && !$('helicorder')) renderHelicorder();
  }

  // ---- Fleet view -------------------------------------------------------------------------
  function renderFleet() {
    const view = $('view');
    if (!fleet) { view.replaceChildren(el('p', {}, 'Waiting for the console…')); return; }
    const sections = fleet.buildings.map(renderBuilding);
    if (!sections.length) sections.push(el('p', { class: 'notice' }, 'No building heard yet: no gateway has answered a status query or sent a heartbeat.'));
    const extra = [];
    if (fleet.malformed_messages) extra.push(el('p', { class: 'notice' }, `${fleet.malformed_messages} messages skipped (did not decode or contradicted their key).`));
    if (fleet.provenance && !fleet.provenance.verifying) extra.push(el('p', { class: 'notice', id: 'on-trust' }, 'Not verified: the console holds no gateway keys (--gateway-key), so what it shows of the gateways is taken on trust.'));
    if (fleet.refused_messages) extra.push(el('p', { class: 'warning', id: 'refused' }, `${fleet.refused_messages} messages dropped: not signed or sealed by their building's gateway.`));
    view.replaceChildren(el('div', { id: 'fleet', 'data-buildings': fleet.buildings.length }, sections, extra));
  }

  function renderBuilding(brief) {
    if (!isExpanded(brief)) return renderBuildingSummary(brief);
    const b = buildingOf(brief);
    const heard = b.last_heard_s === null ? 'never heard' : `last heard ${fmtAge(b.last_heard_s)}`;
    const h = b.history;
    const meta = el('div', { class: 'meta' },
      el('span', {}, `gateway ${b.gateway ?? '?'}`),
      el('span', {}, heard),
      b.started_at && el('span', {}, `started ${fmtTime(Date.parse(b.started_at))}`),
      el('span', { class: 'sensor-count' }, sensorCount(b)),
      b.malformed !== null && el('span', {}, `${b.malformed} malformed payloads`),
      b.dropped !== null && el('span', {}, `${b.dropped} dropped`),
      h && el('span', {}, `history ${fmtBytes(h.bytes)} of ${fmtBytes(h.max_bytes)}` + (h.oldest_ns ? ` since ${fmtTime(nsToMs(h.oldest_ns))}` : '')),
      b.status_error && el('span', { class: 'notice' }, b.status_error));
    const sensorRows = b.sensors.map((s) => renderSensorRow(b, sensorOf(b, s)));
    const table = el('table', {},
      el('thead', {}, el('tr', {}, ['Sensor', 'State', 'Flagged', 'Last seen', 'Samples', 'Gaps (lost)', 'Rejects', 'Mode', 'Calibration', 'Valid until', 'Latest alert'].map((t) => el('th', { title: t === 'Flagged' ? FLAGGED_TITLE : null }, t)))),
      el('tbody', {}, sensorRows));
    const state = b.state === 'up' ? 'up' : b.state === 'down' ? 'down' : 'unknown';
    const listed = b.sensors.filter((s) => s.in_status).length;
    const more = b.total_sensors && b.total_sensors > listed ? el('p', { class: 'meta' }, `Showing ${listed} of ${b.total_sensors} sensors (the first status page).`) : null;
    const worst = b.worst_state;
    return el('section', { class: 'card building', 'data-building': b.building, 'data-state': state, 'data-worst': worst ?? 'none' },
      el('h2', {}, `Building ${b.building} `, worst ? badge(worst, worst.replace(/_/g, ' '), 'the worst state of its sensors') : null,
        badge(state, state === 'up' ? 'gateway up' : state === 'down' ? 'gateway DOWN' : 'no answer'),
        ' ', el('a', { class: 'to-modes', href: `#/modes/${encodeURIComponent(b.building)}`, title: 'its modal frequencies, damping and shapes (triax-modes)' }, 'modes'),
        ' ', el('a', { class: 'to-helicorder', href: `#/helicorder/${encodeURIComponent(b.building)}`, title: '24 h of a channel in rows' }, 'day'),
        fleet.buildings.length > 3 ? [' ', el('button', { class: 'collapse', onclick: () => { expanded.delete(b.building); renderFleet(); } }, 'hide sensors')] : null),
      meta, table, more);
  }

  // A building of a large fleet, folded: its state and the sensors that are not ok.
  function renderBuildingSummary(b) {
    const state = b.state === 'up' ? 'up' : b.state === 'down' ? 'down' : 'unknown';
    const counts = new Map();
    for (const s of b.sensors) counts.set(s.states[0], (counts.get(s.states[0]) || 0) + 1);
    const notOk = b.sensors.filter((s) => s.states[0] !== 'ok');
    return el('section', { class: 'card building folded', 'data-building': b.building, 'data-state': state, 'data-worst': b.worst_state ?? 'none' },
      el('h2', {}, `Building ${b.building} `, b.worst_state ? badge(b.worst_state, b.worst_state.replace(/_/g, ' '), 'the worst state of its sensors') : null,
        badge(state, state === 'up' ? 'gateway up' : state === 'down' ? 'gateway DOWN' : 'no answer'), ' ',
        el('button', { class: 'expand', onclick: () => { expanded.add(b.building); renderFleet(); refreshRows(); } }, 'show sensors')),
      el('div', { class: 'meta' }, el('span', { class: 'sensor-count' }, sensorCount(b)),
        el('span', {}, [...counts].sort().map(([k, n]) => `${n} ${k.replace(/_/g, ' ')}`).join(', '))),
      notOk.length ? el('div', { class: 'not-ok' }, notOk.slice(0, 50).map((s) => el('span', { class: 'sensor-chip' }, el('a', { href: sensorHref(b.building, s.sensor_id) }, s.sensor_id), ' ', s.states.map((st) => badge(st)))),
        notOk.length > 50 ? ` and ${notOk.length - 50} more` : null) : null);
  }

  const FLAGGED_TITLE = 'Share of the samples of the last minute that carry a quality flag (flagged above 20 %)';

  // How many sensors the list shows: the gateway's own, and those heard of only in an alert.
  function sensorCount(b) {
    const listed = b.sensors.filter((s) => s.in_status).length;
    const alertOnly = b.sensors.length - listed;
    const n = Math.max(b.total_sensors ?? 0, listed) + alertOnly;
    return `${n} sensor${n === 1 ? '' : 's'}` + (alertOnly ? ` (${alertOnly} known only from an alert)` : '');
  }

  function shareTitle(f) {
    if (!f) return 'no sample in the last minute';
    const over = f.span_s === null ? 'since the gateway started' : `over the last ${f.span_s.toFixed(0)} s`;
    return `${f.flagged} of ${f.samples} samples flagged ${over}`;
  }

  function renderSensorRow(b, s) {
    const a = s.latest_alert;
    const validity = s.valid_until ? [fmtTime(Date.parse(s.valid_until)), s.expires_in_days !== null && s.expires_in_days < fleet.expiry_warning_days ? el('span', { class: s.expires_in_days <= 0 ? 'warning' : 'notice' }, s.expires_in_days <= 0 ? ' expired' : ` in ${s.expires_in_days.toFixed(1)} d`) : null]
      : s.calibration_version ? 'until superseded' : '—';
    return el('tr', { class: 'sensor', 'data-building': b.building, 'data-sensor': s.sensor_id, 'data-states': s.states.join(' ') },
      el('td', {}, el('a', { href: sensorHref(b.building, s.sensor_id) }, s.sensor_id),
        s.in_status ? null : el('span', { class: 'meta', title: 'not in the gateway\'s status' }, ' (alert only)')),
      el('td', {}, s.states.map((st) => badge(st))),
      el('td', { class: 'num flagged-share', title: shareTitle(s.flagged_share) }, fmtShare(s.flagged_share)),
      el('td', {}, s.last_seen ? fmtAge(s.last_seen_age_s) : 'never'),
      el('td', { class: 'num' }, s.samples),
      el('td', { class: 'num' }, s.gaps ? `${s.gaps} (${s.missing_batches})` : '0'),
      el('td', { class: 'num' }, s.rejects),
      el('td', {}, s.mode),
      el('td', {}, s.calibration_version ? `v${s.calibration_version}` : 'none'),
      el('td', {}, validity),
      el('td', {}, a && a.missing ? el('a', { href: `#/alerts?sensor=${encodeURIComponent(s.sensor_id)}` }, `alert #${a.id}`)
        : a ? [verdict(a), ' ', a.kind.replace(/_/g, ' '), ' ', el('a', { href: sensorHref(b.building, s.sensor_id, alertAtNs(a), windowSpan(a)) }, fmtTime(Date.parse(a.at)))] : '—'));
  }

  // The middle of the window the alert judged (its own times, by the sensor's clock); the
  // service's clock for an alert that names none (stale, or an older service).
  const alertAtNs = (a) => (a.window_start_ns != null && a.window_end_ns != null)
    ? Math.round((a.window_start_ns + a.window_end_ns) / 2) : msToNs(Date.parse(a.at));
  // Arriving from an alert, the sensor view shades the window it judged and draws its threshold.
  const alertLinkExtra = (a) => `&alert=${a.id}`;
  const windowSpan = (a) => Math.min(3600, Math.max(30, Math.ceil((a.window_s || 10) * 3)));

  // ---- Alerts view ------------------------------------------------------------------------
  // The alert log (/api/alerts), filtered by the URL's query. The table is built once per
  // route; refreshes update rows in place by alert id, so a row under the cursor, an open
  // statement or a ticked box stays as it is while alerts arrive.
  const KINDS = ['peak_acceleration', 'rms_acceleration', 'dominant_frequency', 'tilt_change', 'stale', 'modal_shift'];
  const LEVELS = ['exceeded', 'possible', 'stale', 'unverified'];
  const STATES = ['all', 'open', 'acknowledged', 'silenced'];
  const SINCE = [['', 'any time'], ['3600', 'last 1 h'], ['86400', 'last 24 h'], ['604800', 'last 7 d'], ['2592000', 'last 30 d']];
  let alertsSeen = null;     // fleet counters the alert table was last fetched at
  let alertsFetching = false;

  function alertFilter() {
    const f = {};
    for (const k of ['building', 'sensor', 'kind', 'level', 'state', 'since_s']) { const v = route.params.get(k); if (v) f[k] = v; }
    return f;
  }

  function renderAlerts() {
    const f = alertFilter();
    const sel = (id, values, current, label) => el('label', {}, label, ' ', el('select', { id, onchange: changeFilter },
      values.map(([v, t]) => el('option', { value: v, selected: v === (current || '') ? 'selected' : null }, t))));
    const buildings = fleet ? fleet.buildings.map((b) => b.building) : [];
    if (f.building && !buildings.includes(f.building)) buildings.push(f.building);
    const sensorInput = el('input', { id: 'f-sensor', type: 'text', size: 10, value: f.sensor || '', placeholder: 'any' });
    sensorInput.addEventListener('change', changeFilter);
    const silenceFor = el('select', { id: 'silence-for' }, [[3600, '1 h'], [14400, '4 h'], [86400, '24 h'], [604800, '7 d']].map(([v, t]) => el('option', { value: v }, t)));
    $('view').replaceChildren(el('section', { class: 'card', id: 'alerts' },
      el('h2', {}, 'Alerts'),
      el('p', { class: 'meta' }, 'Guard band: exceeded when value − k·u is above the threshold, possible when the interval [value − k·u, value + k·u] contains it. Acknowledging or silencing an alert records who and when; it never changes its verdict or the sensor\'s state.'),
      el('div', { class: 'controls', id: 'alert-filters' },
        sel('f-building', [['', 'any'], ...buildings.map((b) => [b, b])], f.building, 'building'),
        el('label', {}, 'sensor ', sensorInput),
        sel('f-kind', [['', 'any'], ...KINDS.map((k) => [k, k.replace(/_/g, ' ')])], f.kind, 'kind'),
        sel('f-level', [['', 'any'], ...LEVELS.map((k) => [k, k])], f.level, 'level'),
        sel('f-state', STATES.map((k) => [k === 'all' ? '' : k, k]), f.state, 'state'),
        sel('f-since', SINCE, f.since_s, 'time')),
      el('div', { class: 'controls' },
        el('span', { class: 'meta', id: 'acting-as' }, me && me.operator ? `acting as ${me.operator.name} (${me.operator.role})` : 'log in to acknowledge or silence'),
        el('button', { id: 'ack-selected', onclick: () => acknowledge(checkedIds()) }, 'Acknowledge selected'),
        el('span', { class: 'meta' }, 'silence for ', silenceFor)),
      el('div', { id: 'alerts-status', class: 'meta' }, 'reading the alert log…'),
      el('div', { id: 'notify-status', class: 'meta' }),
      el('table', { id: 'alert-table' },
        el('thead', {}, el('tr', {}, ['At', 'Sensor', 'Verdict', 'Kind', 'Value ± k·u', 'Threshold', 'Interval', 'Window', 'Flagged', 'Statement', 'Handled', 'Select'].map((t) => el('th', {}, t)))),
        el('tbody', { id: 'alert-rows' }))),
    el('section', { class: 'card', id: 'silences' }, el('h3', {}, 'Silences'), el('div', { id: 'silence-list' })));
    alertsSeen = null;
    refreshAlerts();
  }

  function changeFilter() {
    const q = new URLSearchParams();
    const put = (k, v) => { if (v) q.set(k, v); };
    put('building', $('f-building').value); put('sensor', $('f-sensor').value.trim());
    put('kind', $('f-kind').value); put('level', $('f-level').value);
    put('state', $('f-state').value); put('since_s', $('f-since').value);
    location.hash = '#/alerts' + (q.toString() ? '?' + q : '');
  }

  const checkedIds = () => [...document.querySelectorAll('#alert-rows input.pick:checked')].map((c) => Number(c.closest('tr').dataset.id));

  async function refreshAlerts() {
    if (!route || route.view !== 'alerts' || alertsFetching) return;
    const seen = fleet ? `${fleet.alerts_total}:${fleet.alerts_open}` : '';
    if (alertsSeen === seen) return;
    alertsFetching = true;
    const f = alertFilter();
    const q = new URLSearchParams();
    for (const k of ['building', 'sensor', 'kind', 'level', 'state']) if (f[k]) q.set(k, f[k]);
    if (f.since_s && /^\d+$/.test(f.since_s)) q.set('from_ns', msToNs(Date.now() - Number(f.since_s) * 1000));
    const myRoute = route;
    const [body, silences, notes] = await Promise.all([getJson('/api/alerts?' + q), getJson('/api/silences'), getJson('/api/notifications')]);
    alertsFetching = false;
    if (route !== myRoute) return;
    alertsSeen = seen;
    const status = $('alerts-status');
    if (body.error) { status.textContent = body.error; status.className = 'warning'; return; }
    status.className = 'meta';
    status.textContent = `${body.matched} alert${body.matched === 1 ? '' : 's'} match` + (body.matched > body.alerts.length ? ` (the newest ${body.alerts.length} shown)` : '') +
      `; the log keeps ${body.kept} (at most ${body.max_alerts}, ${body.retention_days} days)` + (body.file ? ` in ${body.file}` : ', in memory only') + `; ${body.open} open.`;
    updateAlertRows(body.alerts);
    if (!silences.error) renderSilences(silences);
    if (!notes.error) renderNotifyStatus(notes);
  }

  function statementCell(text) {
    const first = String(text).split('\n')[0];
    const short = first.length > 90 ? first.slice(0, 89) + '…' : first;
    return el('td', { class: 'statement-cell' }, el('details', {}, el('summary', {}, short), el('div', { class: 'statement full' }, text)));
  }

  function handledCell(a) {
    const td = el('td', { class: 'handled' });
    if (a.ack) td.append(badge('acknowledged', 'acknowledged', a.ack.note || null), ` by ${a.ack.by}, ${fmtTime(Date.parse(a.ack.at))}`);
    else td.append(el('button', { class: 'ack', onclick: () => acknowledge([a.id]) }, 'Acknowledge'));
    if (a.silenced_by !== null && a.silenced_by !== undefined) td.append(' ', badge('silenced', `silenced (#${a.silenced_by})`));
    td.append(' ', el('button', { class: 'silence', title: `silence ${a.building} / ${a.sensor_id}, ${a.kind.replace(/_/g, ' ')}`, onclick: () => silence(a) }, 'Silence'));
    return td;
  }

  function alertRow(a) {
    const k = a.coverage_factor, u = a.standard_uncertainty;
    return el('tr', { class: 'alert', 'data-id': a.id, 'data-building': a.building, 'data-sensor': a.sensor_id, 'data-level': verified(a) ? a.level : 'unverified', 'data-trust': a.trust },
      el('td', {}, fmtTime(Date.parse(a.at))),
      el('td', {}, el('a', { href: sensorHref(a.building, a.sensor_id, alertAtNs(a), windowSpan(a)) + alertLinkExtra(a) }, `${a.building} / ${a.sensor_id}`),
        ' ', el('a', { class: 'to-building', href: `#/building/${encodeURIComponent(a.building)}?at=${alertAtNs(a)}&span=${windowSpan(a)}&alert=${a.id}`, title: 'every sensor of the building at that time' }, '(building)')),
      el('td', {}, verdict(a), a.late ? badge('late', 'late', 'raised from data recovered from the history') : null),
      el('td', {}, a.kind.replace(/_/g, ' ')),
      el('td', { class: 'num' }, a.level === 'stale' ? '—' : `${fmtNum(a.value)} ± ${fmtNum(k * u, 2)} ${fmtUnit(a.unit)}`),
      el('td', { class: 'num' }, a.level === 'stale' ? '—' : `${fmtNum(a.threshold)} ${fmtUnit(a.unit)}`),
      el('td', { class: 'num' }, a.level === 'stale' ? '—' : `[${fmtNum(a.value - k * u)}, ${fmtNum(a.value + k * u)}]`),
      el('td', { class: 'num' }, `${fmtNum(a.window_s, 3)} s`),
      el('td', { class: 'num' }, `${(100 * a.flagged_fraction).toFixed(0)} %`),
      statementCell(a.statement),
      handledCell(a),
      // Last, so that the columns before keep their places for whoever reads them by index.
      el('td', {}, el('input', { type: 'checkbox', class: 'pick', 'aria-label': `select alert ${a.id}` })));
  }

  const handledKey = (a) => `${a.ack ? a.ack.at : ''}|${a.silenced_by ?? ''}`;

  function updateAlertRows(alerts) {
    const body = $('alert-rows');
    if (!body) return;
    const rows = new Map([...body.children].map((tr) => [tr.dataset.id, tr]));
    const wanted = new Set(alerts.map((a) => String(a.id)));
    for (const [id, tr] of rows) if (!wanted.has(id)) tr.remove();
    let at = 0;
    for (const a of alerts) {
      let tr = rows.get(String(a.id));
      if (!tr) tr = alertRow(a);
      else if (tr.dataset.handled !== handledKey(a)) tr.querySelector('td.handled').replaceWith(handledCell(a));
      tr.dataset.handled = handledKey(a);
      if (body.children[at] !== tr) body.insertBefore(tr, body.children[at] || null);
      at++;
    }
    if (!alerts.length && !body.children.length) $('alerts-status').textContent += ' None to show.';
  }

  // What notifications left the console (--notify-config), and the last one.
  function renderNotifyStatus(n) {
    const box = $('notify-status');
    if (!box) return;
    if (!n.configured) { box.textContent = 'Notifications: none configured (--notify-config).'; return; }
    const last = n.recent && n.recent[0];
    box.replaceChildren(`Notifications on ${n.channels.join(', ')}: ${n.sent} sent, `, el('span', { class: n.failed ? 'warning' : null }, `${n.failed} failed`),
      `, ${n.held} held for quiet hours, ${n.unrouted} not routed` + (n.dropped ? `, ${n.dropped} dropped (queue full)` : ''),
      last ? `; last: ${last.kind} on ${last.channel} at ${fmtTime(nsToMs(last.at_ns))}` + (last.error ? ` (failed: ${last.error})` : '') : '');
    box.dataset.sent = String(n.sent);
  }

  function renderSilences(list) {
    const box = $('silence-list');
    if (!box) return;
    if (!list.length) { box.replaceChildren(el('p', { class: 'meta' }, 'None.')); return; }
    box.replaceChildren(el('table', {}, el('tbody', {}, list.map((s) => el('tr', { class: 'silence', 'data-id': s.id, 'data-active': s.active ? 'true' : 'false' },
      el('td', {}, `#${s.id}`),
      el('td', {}, `${s.building} / ${s.sensor ?? 'every sensor'}, ${s.kind ? s.kind.replace(/_/g, ' ') : 'every kind'}`),
      el('td', {}, `${fmtTime(Date.parse(s.from))} – ${fmtTime(Date.parse(s.until))}`),
      el('td', {}, `by ${s.by}`, s.reason ? ` (${s.reason})` : ''),
      el('td', {}, s.lifted ? `lifted by ${s.lifted.by}, ${fmtTime(Date.parse(s.lifted.at))}` : s.active ? el('button', { class: 'lift', onclick: () => post('/api/alerts/lift', { id: s.id }) }, 'Lift') : 'ended'))))));
  }

  // A write to the alert log; what the console answered is shown, a refusal included.
  async function post(path, body) {
    const status = $('alerts-status');
    if (!me || !me.operator) { status.textContent = 'Log in first (top right): acknowledgements and silences record who and when.'; status.className = 'warning'; return null; }
    let resp, text;
    try {
      resp = await fetch(path, { method: 'POST', headers: { 'Content-Type': 'application/json' }, body: JSON.stringify(body) });
      text = await resp.text();
    } catch (e) { status.textContent = `console unreachable (${e.message || e})`; status.className = 'warning'; return null; }
    if (!resp.ok) { status.textContent = `console refused (${resp.status}): ${text.trim()}`; status.className = 'warning'; return null; }
    alertsSeen = null;
    refreshAlerts();
    return JSON.parse(text);
  }

  function acknowledge(ids) {
    if (!ids.length) { $('alerts-status').textContent = 'No alert selected.'; return; }
    post('/api/alerts/ack', { ids });
  }

  function silence(a) {
    post('/api/alerts/silence', { building: a.building, sensor: a.sensor_id, kind: a.kind, duration_s: Number($('silence-for').value) });
  }

  // ---- Sensor view ------------------------------------------------------------------------
  function plotWidth() {
    return Math.max(50, Math.min(4000, Math.round(($('view').clientWidth || 1000) - 4)));
  }

  // The light live stream: as chosen on this browser, else when it says that its link is
  // slow or metered (Network Information API, where there is one).
  function liteStream() {
    const chosen = localStorage.getItem('triax.lite');
    if (chosen !== null) return chosen === '1';
    const c = navigator.connection;
    return !!(c && (c.saveData || ['slow-2g', '2g', '3g'].includes(c.effectiveType)));
  }

  function renderSensor() {
    const r = route;
    live = null; tilt = []; historyView = null; detail = null;
    trendView = null; spectrumView = null; spectrogramView = null; alertInfo = null; processedView = null;
    const isLive = !r.window;
    const spanS = isLive ? Math.min(r.span, LIVE_MAX_SPAN_S) : r.span;
    // The span asked for is listed even if it is not one of the usual ones.
    const spans = [...new Set([...SPANS_S, spanS])].sort((a, b) => a - b).filter((s) => !isLive || s <= LIVE_MAX_SPAN_S);
    const spanSel = el('select', { id: 'span', onchange: (e) => navigate({ span: Number(e.target.value) }) },
      spans.map((s) => el('option', { value: s, selected: s === spanS ? 'selected' : null }, fmtSpan(s))));
    const atMs = isLive ? Date.now() : r.at / 1e6;
    const atInput = el('input', { id: 'at', type: 'text', size: 19, spellcheck: 'false', placeholder: 'YYYY-MM-DD HH:MM:SS', value: fmtInput(atMs) });
    const lookBack = () => {
      const ms = parseInput(atInput.value);
      if (ms === null) {
        atInput.setAttribute('aria-invalid', 'true');
        $('status-line').textContent = `"${atInput.value}" is not a time like ${fmtInput(Date.now())} (${zoneLabel()})`;
      } else navigate({ at: msToNs(ms) });
    };
    atInput.addEventListener('keydown', (e) => { if (e.key === 'Enter') lookBack(); });
    const controls = el('div', { class: 'controls' },
      el('button', { id: 'btn-live', class: isLive ? 'active' : '', onclick: () => navigate({ at: null }) }, 'Live'),
      el('button', { id: 'btn-back', onclick: () => step(-1), title: 'one span back' }, '◀'),
      el('label', {}, `at (${zoneLabel()}) `, atInput),
      el('button', { id: 'btn-go', onclick: lookBack }, 'Look back'),
      el('button', { id: 'btn-fwd', onclick: () => step(1), title: 'one span forward, up to now', disabled: isLive || atMs >= latestAtMs(spanS) - 1000 ? 'disabled' : null }, '▶'),
      el('label', {}, 'span ', spanSel),
      el('span', { class: 'meta' }, 'last'),
      [[900, '15 min'], [3600, '1 h'], [86400, '24 h'], [604800, '7 d']].map(([n, t]) => el('button', { class: `last${r.last === n ? ' active' : ''}`, 'data-last': n, onclick: () => { location.hash = sensorBase() + `?last=${n}` + (r.alert ? `&alert=${r.alert}` : '') + processingExtra(r); } }, t)),
      isLive ? el('label', { title: 'for slow links: a frame a second with only the buckets that changed, the fleet deltas every 5 s (about a fifth of the bytes)' }, el('input', { id: 'lite', type: 'checkbox', checked: liteStream() ? 'checked' : null, onchange: (e) => { localStorage.setItem('triax.lite', e.target.checked ? '1' : '0'); renderSensor(); } }), ' light stream') : null,
      el('label', { title: 'acceleration as corrected, or band-passed, or integrated to velocity or displacement within the band (history views)' }, 'show ',
        el('select', { id: 'quantity' }, Object.keys(QUANTITIES).map((q) => el('option', { value: q, selected: q === r.quantity ? 'selected' : null }, q)))),
      el('label', { title: 'the band in Hz, LOW-HIGH; either may be left out (velocity and displacement need LOW)' }, 'band ', el('input', { id: 'band', type: 'text', size: 8, spellcheck: 'false', placeholder: '0.1-20', value: r.band })), ' Hz ',
      el('button', { id: 'btn-process', onclick: applyProcessing }, 'Apply'),
      el('button', { id: 'btn-spectrum', onclick: loadSpectrum, title: 'power spectral density per axis of the span shown' }, 'Spectrum'),
      el('button', { id: 'btn-spectrogram', onclick: loadSpectrogram, title: 'spectrogram of one axis over the span shown: its PSD per column of time' }, 'Spectrogram'),
      el('button', { id: 'btn-csv', onclick: exportCsv, title: 'every sample of the span shown (up to 1 h), as CSV' }, 'CSV'),
      el('button', { id: 'btn-mseed', onclick: exportMseed, title: 'every calibrated sample of the span shown (up to 1 h), as miniSEED 2: acceleration (location 00), standard uncertainty (U0) and flags (Q0) per axis' }, 'miniSEED'),
      el('button', { id: 'btn-png', onclick: () => exportImage('png') }, 'PNG'),
      el('button', { id: 'btn-svg', onclick: () => exportImage('svg') }, 'SVG'),
      el('a', { id: 'btn-day', href: `#/helicorder/${encodeURIComponent(r.building)}/${encodeURIComponent(r.sensor)}`, title: '24 h of a channel in rows (helicorder)' }, 'day'),
      el('a', { id: 'btn-building', href: `#/building/${encodeURIComponent(r.building)}` + (r.window ? `?from=${msToNs(r.window[0])}&to=${msToNs(r.window[1])}` : '') + (r.alert ? `${r.window ? '&' : '?'}alert=${r.alert}` : '') }, 'building view'));
    const plots = el('div', { id: 'plot', 'data-source': r.error ? 'none' : isLive ? 'live' : 'history', 'data-frames': 0, 'data-buckets': 0, 'data-gaps': 0, 'data-tilt-points': 0 },
      AXES.map((ax) => el('div', { class: 'plot' }, el('canvas', { id: `canvas-${ax}`, width: 1000, height: 170 }), el('span', { class: 'title', id: `title-${ax}` }, `a${ax}`))),
      el('div', { class: 'plot', id: 'tilt-plot', hidden: 'hidden' }, el('canvas', { id: 'canvas-tilt', width: 1000, height: 170 }), el('span', { class: 'title' }, 'tilt: roll (blue), pitch (green), degrees, ±k·u shaded')),
      el('div', { class: 'plot', id: 'freq-plot', hidden: 'hidden' }, el('canvas', { id: 'canvas-freq', width: 1000, height: 170 }), el('span', { class: 'title' }, 'dominant frequency per minute (Hz), from zero crossings')),
      el('div', { class: 'legend', id: 'legend' }),
      el('div', { id: 'readout', hidden: 'hidden' }),
      el('div', { id: 'selection', hidden: 'hidden' }));
    $('view').replaceChildren(el('section', { class: 'card', id: 'sensor', 'data-building': r.building, 'data-sensor': r.sensor },
      el('h2', {}, el('a', { href: '#/' }, r.building), ' / ', r.sensor),
      el('div', { id: 'sensor-header', class: 'meta' }),
      controls,
      r.error ? el('div', { id: 'status-line', class: 'warning', 'data-error': 'link' }, `This link cannot be shown: ${r.error}.`)
        : el('div', { id: 'status-line', class: 'meta' }, isLive ? 'waiting for the live stream…' : 'reading the history…'),
      plots),
    el('section', { class: 'card', id: 'spectrum', hidden: 'hidden' }, el('h3', {}, 'Spectrum'), el('div', { id: 'spectrum-line', class: 'meta' }),
      el('div', { class: 'plot' }, el('canvas', { id: 'canvas-psd', width: 1000, height: 260 }), el('span', { class: 'title' }, 'PSD per axis, (m/s²)²/Hz, log–log; 95 % band (χ², 2·segments degrees of freedom) shaded'))),
    el('section', { class: 'card', id: 'spectrogram', hidden: 'hidden' }, el('h3', {}, 'Spectrogram'),
      el('div', { class: 'controls' }, el('label', {}, 'axis ', el('select', { id: 'spectrogram-axis', onchange: loadSpectrogram }, AXES.map((a) => el('option', { value: a }, a))))),
      el('div', { id: 'spectrogram-line', class: 'meta' }),
      el('div', { class: 'plot' }, el('canvas', { id: 'canvas-spectrogram', width: 1000, height: 260 }), el('span', { class: 'title', id: 'spectrogram-title' }, 'PSD per column of time, dB re 1 (m/s²)²/Hz'))),
    el('section', { class: 'card', id: 'calibration' }, el('h3', {}, 'Calibration in force'), el('div', { id: 'record' }, 'asking the gateway…')),
    notesPanel(r.building, r.sensor),
    el('section', { class: 'card' }, el('h3', {}, 'Alerts of this sensor'), el('div', { id: 'sensor-alerts' })));
    renderSensorHeader();
    refreshRows();
    loadDetail();
    if (r.error) { connect(''); return; }
    const q = new URLSearchParams({ building: r.building, sensor: r.sensor, span_s: String(spanS), width: String(plotWidth()) });
    if (liteStream()) q.set('lite', '1');
    $('plot').dataset.stream = liteStream() ? 'light' : 'full';
    for (const c of document.querySelectorAll('#plot canvas')) attachPointer(c, () => scheduleDraw());
    if (r.alert) loadAlert(r.alert);
    loadNotes(r.building, ...(r.window || [Date.now() - LIVE_MAX_SPAN_S * 1000, Date.now() + 3600e3]));
    if (isLive) connect(q.toString());
    else { connect(''); loadWindow(r.window); }
  }

  const sensorBase = () => `#/sensor/${encodeURIComponent(route.building)}/${encodeURIComponent(route.sensor)}`;

  // The quantity and band chosen: the window shown (a live one as history) read again so.
  function applyProcessing() {
    const r = { ...route, quantity: $('quantity').value, band: $('band').value.trim().replace(/\s+/g, '') };
    if (r.quantity !== 'acceleration' && !/^[0-9.]+-/.test(r.band)) r.band = '0.1-' + (r.band.split('-')[1] || '');
    const [fromMs, toMs] = currentWindow();
    location.hash = sensorBase() + `?from=${msToNs(fromMs)}&to=${msToNs(toMs)}` + (route.alert ? `&alert=${route.alert}` : '') + processingExtra(r);
  }

  // The alert a link came from: its window is shaded and its threshold drawn.
  async function loadAlert(id) {
    const myRoute = route;
    const body = await getJson(`/api/alerts?id=${id}`);
    if (route !== myRoute || body.error || !body.alerts.length) return;
    alertInfo = body.alerts[0];
    scheduleDraw();
  }

  // A window of up to an hour is read from the history and decimated per pixel column; a
  // longer one is a trend of per-minute aggregates.
  function loadWindow(win) {
    if ((win[1] - win[0]) / 1000 > HISTORY_MAX_SPAN_S) loadTrend(win[0], win[1]);
    else if (processing(route)) loadProcessed(win[0], win[1]);
    else loadHistoryWindow(win[0], win[1]);
  }

  let processedView = null;  // /api/processed answer of the sensor view
  const processedQuery = (building, sensor, fromMs, toMs, quantity, band) => {
    const q = new URLSearchParams({ building, sensor, from_ns: msToNs(fromMs), to_ns: msToNs(toMs), width: String(plotWidth()), quantity });
    if (band) q.set('band', band);
    return '/api/processed?' + q;
  };
  async function loadProcessed(fromMs, toMs) {
    const myRoute = route;
    $('status-line').textContent = `computing ${route.quantity} in ${route.band} Hz…`;
    const body = await getJson(processedQuery(route.building, route.sensor, fromMs, toMs, route.quantity, route.band));
    if (route !== myRoute) return;
    if (!body.view) { $('status-line').textContent = `${route.quantity}: ${body.error}`; return; }
    processedView = { ...body, fromMs, toMs };
    const v = body.view;
    $('plot').dataset.source = 'processed';
    $('plot').dataset.buckets = v.buckets.length;
    $('status-line').textContent = `${v.quantity} (${v.unit}), band ${bandText(v.band)}: ${v.samples_used} samples in ${v.runs.length} runs` + (v.runs_too_short ? `, ${v.runs_too_short} runs under 1 s left out` : '') +
      `; ${v.filter}; ${body.settle_s} s read on either side for the filters to settle; no ±k·u band (not stated for filtered or integrated values)` + (body.error ? `; ${body.error}` : '');
    scheduleDraw();
  }
  const bandText = (b) => `${b.low_hz ?? '0'}–${b.high_hz ?? 'Nyquist'} Hz`;

  // A processed view as plot series: per bucket min and max, broken between runs.
  function processedSeries(v, axes, name, colors) {
    const bucketMs = v.bucket_ns / 1e6;
    const starts = new Set(v.runs.map((r) => Math.floor(r[0] / v.bucket_ns)));
    const gaps = [];
    for (let i = 1; i < v.runs.length; i++) gaps.push({ start_ns: v.runs[i - 1][1], end_ns: v.runs[i][0] });
    return {
      bucketMs, gaps,
      series: axes.map((i, k) => ({ name: name(i), color: colors[k], points: v.buckets.map((b) => ({ t: (b[0] + 0.5) * bucketMs, min: b[1 + 2 * i], max: b[2 + 2 * i], lo: null, hi: null, flags: 0, gap: starts.has(b[0]) })) })),
    };
  }

  async function loadTrend(fromMs, toMs) {
    const q = new URLSearchParams({ building: route.building, sensor: route.sensor, from_ns: msToNs(fromMs), to_ns: msToNs(toMs) });
    const myRoute = route;
    $('status-line').textContent = 'reading per-minute aggregates…';
    const body = await getJson('/api/trend?' + q);
    if (route !== myRoute) return;
    trendView = { ...body, fromMs, toMs };
    $('plot').dataset.source = 'trend';
    $('plot').dataset.minutes = body.minutes ? body.minutes.length : 0;
    $('status-line').textContent = body.error && !body.minutes ? `trend: ${body.error}` :
      `trend: ${body.minutes.length} minutes (peak and RMS about each minute's mean)` + (body.batches_read ? `, ${body.batches_read} batches read from the history` : ', all from the console\'s cache') + (body.error ? `; ${body.error}` : '');
    scheduleDraw();
  }

  // The span the view shows now, [fromMs, toMs].
  function currentWindow() {
    if (route.window) return route.window;
    if (live) { const to = nsToMs(live.end_ns); return [to - nsToMs(live.span_ns), to]; }
    return [Date.now() - route.span * 1000, Date.now()];
  }

  function navigateWindow(fromMs, toMs) {
    const now = Date.now();
    if (toMs > now) { fromMs -= toMs - now; toMs = now; }
    location.hash = sensorOrBuildingBase() + `?from=${msToNs(fromMs)}&to=${msToNs(toMs)}` + (route.alert ? `&alert=${route.alert}` : '') + (route.view === 'building' && route.axis !== 'x' ? `&axis=${route.axis}` : '') + processingExtra();
  }
  const sensorOrBuildingBase = () => route.view === 'building' ? `#/building/${encodeURIComponent(route.building)}` : sensorBase();

  // Drag to zoom, Shift-drag to pan, hover for the values under the cursor.
  function attachPointer(canvas, redraw) {
    let drag = null;
    const sel = () => $('selection');
    const pos = (e) => { const m = canvas._map; const r = canvas.getBoundingClientRect(); return m ? { x: e.clientX - r.left, t: m.x0 + (e.clientX - r.left - m.left) / m.pw * (m.x1 - m.x0), m, r } : null; };
    canvas.addEventListener('mousedown', (e) => { const p = pos(e); if (p) { drag = { x: p.x, t: p.t, pan: e.shiftKey }; e.preventDefault(); } });
    canvas.addEventListener('mousemove', (e) => {
      const p = pos(e);
      if (!p) return;
      if (drag && !drag.pan) {
        const s = sel(); const a = Math.min(drag.x, p.x), b = Math.max(drag.x, p.x);
        s.hidden = false; s.style.left = `${p.r.left + window.scrollX + a}px`; s.style.width = `${b - a}px`;
        s.style.top = `${p.r.top + window.scrollY}px`; s.style.height = `${p.r.height}px`;
      }
      readout(canvas, p, e);
    });
    canvas.addEventListener('mouseleave', () => { const r = $('readout'); if (r) r.hidden = true; });
    canvas.addEventListener('mouseup', (e) => {
      const p = pos(e);
      const d = drag; drag = null;
      if (sel()) sel().hidden = true;
      if (!d || !p) return;
      if (d.pan) {
        const dt = d.t - p.t;
        if (Math.abs(p.x - d.x) >= 3) navigateWindow(p.m.x0 + dt, p.m.x1 + dt);
      } else if (Math.abs(p.x - d.x) >= 5) {
        const a = Math.min(d.t, p.t), b = Math.max(d.t, p.t);
        navigateWindow(a, Math.max(b, a + 1000));
      }
    });
  }

  // The values of the bucket under the cursor: value (or its range) ± k·u per series, flags,
  // calibration version and k.
  function readout(canvas, p, e) {
    const box = $('readout');
    const m = p.m;
    if (!box || !m.series) return;
    const lines = [fmtTime(p.t) + (m.bucketMs ? ` (${m.bucketMs >= 1000 ? (m.bucketMs / 1000).toFixed(1) + ' s' : m.bucketMs.toFixed(0) + ' ms'} per point)` : '')];
    let flags = 0;
    for (const s of m.series) {
      let best = null;
      for (const q of s.points) if (!best || Math.abs(q.t - p.t) < Math.abs(best.t - p.t)) best = q;
      if (!best || best.min === null) continue;
      flags |= best.flags || 0;
      const ku = best.hi !== null && best.hi !== undefined && Number.isFinite(best.hi) ? best.hi - best.max : null;
      const v = best.min === best.max ? fmtNum(best.min, 5) : `${fmtNum(best.min, 5)} … ${fmtNum(best.max, 5)}`;
      lines.push(`${s.name || ''}: ${v}${ku !== null ? ` ± ${fmtNum(ku, 2)}` : ''} ${m.unit || ''}`);
    }
    if (m.correction) lines.push(`calibration v${m.correction.calibration_version}, k = ${fmtK(m.correction.coverage_factor)}`);
    lines.push(flags ? `flags: ${flagNames(flags).join(', ')}` : 'no flags');
    box.replaceChildren(...lines.map((l) => el('div', {}, l)));
    box.hidden = false;
    box.style.left = `${e.clientX + window.scrollX + 14}px`;
    box.style.top = `${e.clientY + window.scrollY + 10}px`;
  }

  async function loadSpectrum() {
    const [fromMs, toMs] = currentWindow();
    const box = $('spectrum');
    box.hidden = false;
    const line = $('spectrum-line');
    if ((toMs - fromMs) / 1000 > HISTORY_MAX_SPAN_S) { line.textContent = 'A spectrum is computed over at most 1 h: zoom in first.'; return; }
    line.textContent = `computing the spectrum of ${fmtTime(fromMs)} – ${fmtTime(toMs)}…`;
    const myRoute = route;
    const body = await getJson('/api/spectrum?' + new URLSearchParams({ building: route.building, sensor: route.sensor, from_ns: msToNs(fromMs), to_ns: msToNs(toMs) }));
    if (route !== myRoute) return;
    spectrumView = body.spectrum || null;
    if (!spectrumView) { line.textContent = `spectrum: ${body.error}`; return; }
    const sp = spectrumView;
    line.replaceChildren(`${fmtTime(fromMs)} – ${fmtTime(toMs)}: ${sp.segments} segments of ${sp.segment_samples} samples (Hann, half overlap), ${fmtNum(sp.resolution_hz, 3)} Hz resolution, ${sp.degrees_of_freedom} degrees of freedom. Peaks: `,
      el('span', { id: 'spectrum-peaks' }, AXES.map((a, i) => `${a} ${sp.axes[i].peak_hz === null ? '—' : fmtNum(sp.axes[i].peak_hz, 3) + ' Hz'}`).join(', ')),
      body.error ? ` (${body.error})` : '');
    drawSpectrum();
  }

  function drawSpectrum() {
    const sp = spectrumView;
    const canvas = $('canvas-psd');
    if (!sp || !canvas) return;
    const c = colors();
    const dpr = window.devicePixelRatio || 1;
    const w = Math.max(50, canvas.clientWidth), h = canvas.clientHeight || 260;
    canvas.width = Math.round(w * dpr); canvas.height = Math.round(h * dpr);
    const g = canvas.getContext('2d');
    g.setTransform(dpr, 0, 0, dpr, 0, 0);
    g.fillStyle = c.bg; g.fillRect(0, 0, w, h);
    const left = 62, right = 8, top = 20, bottom = 20, pw = w - left - right, ph = h - top - bottom;
    const f = sp.frequencies_hz;
    const f0 = f[1], f1 = f[f.length - 1];
    let lo = Infinity, hi = -Infinity;
    for (const a of sp.axes) for (let k = 1; k < f.length; k++) { if (a.lo[k] > 0) lo = Math.min(lo, a.lo[k]); if (a.hi[k] > 0) hi = Math.max(hi, a.hi[k]); }
    if (!Number.isFinite(lo)) { lo = 1e-12; hi = 1; }
    const L = Math.log10, X = (x) => left + (L(x) - L(f0)) / (L(f1) - L(f0)) * pw, Y = (v) => top + (L(hi) - L(Math.max(v, lo))) / (L(hi) - L(lo)) * ph;
    g.font = '11px system-ui, sans-serif'; g.fillStyle = c.muted; g.strokeStyle = c.grid;
    for (let d = Math.ceil(L(lo)); d <= L(hi); d++) { const y = Y(10 ** d); g.beginPath(); g.moveTo(left, y); g.lineTo(left + pw, y); g.stroke(); g.fillText(`1e${d}`, 4, y + 4); }
    for (let d = Math.ceil(L(f0)); d <= L(f1); d++) for (const m of [1, 2, 5]) { const x = 10 ** d * m; if (x < f0 || x > f1) continue; const px = X(x); g.beginPath(); g.moveTo(px, top); g.lineTo(px, top + ph); g.stroke(); g.fillText(`${x} Hz`, px + 2, h - 6); }
    sp.axes.forEach((a, i) => {
      g.fillStyle = AXIS_COLORS[i] + '2a'; g.beginPath();
      for (let k = 1; k < f.length; k++) (k === 1 ? g.moveTo(X(f[k]), Y(a.hi[k])) : g.lineTo(X(f[k]), Y(a.hi[k])));
      for (let k = f.length - 1; k >= 1; k--) g.lineTo(X(f[k]), Y(a.lo[k]));
      g.closePath(); g.fill();
      g.strokeStyle = AXIS_COLORS[i]; g.lineWidth = 1.2; g.beginPath();
      for (let k = 1; k < f.length; k++) (k === 1 ? g.moveTo(X(f[k]), Y(a.psd[k])) : g.lineTo(X(f[k]), Y(a.psd[k])));
      g.stroke();
    });
    g.strokeStyle = c.frame; g.strokeRect(left, top, pw, ph);
    canvas.dataset.drawn = String(f.length);
  }

  async function loadSpectrogram() {
    const [fromMs, toMs] = currentWindow();
    $('spectrogram').hidden = false;
    const line = $('spectrogram-line');
    if ((toMs - fromMs) / 1000 > HISTORY_MAX_SPAN_S) { line.textContent = 'A spectrogram is computed over at most 1 h: zoom in first.'; return; }
    const axis = $('spectrogram-axis').value;
    line.textContent = `computing the spectrogram of a${axis}, ${fmtTime(fromMs)} – ${fmtTime(toMs)}…`;
    const myRoute = route;
    // 60 columns: finer ones would pay for time resolution with frequency resolution (a
    // column's segment fits in it), and the modes sought change slowly.
    const columns = 60;
    const body = await getJson('/api/spectrogram?' + new URLSearchParams({ building: route.building, sensor: route.sensor, from_ns: msToNs(fromMs), to_ns: msToNs(toMs), axis, columns: String(columns) }));
    if (route !== myRoute) return;
    spectrogramView = body.spectrogram || null;
    if (!spectrogramView) { line.textContent = `spectrogram: ${body.error}`; delete $('canvas-spectrogram').dataset.drawn; return; }
    const g = spectrogramView;
    line.replaceChildren(`a${g.axis}, ${fmtTime(fromMs)} – ${fmtTime(toMs)}: ${g.psd_db.length} columns of ${fmtNum(g.column_ns / 1e9, 3)} s, segments of ${g.segment_samples} samples (Hann, half overlap), ${fmtNum(g.resolution_hz, 3)} Hz resolution. Strongest over the span: `,
      el('span', { id: 'spectrogram-peak' }, g.peak_hz === null ? '—' : `${fmtNum(g.peak_hz, 3)} Hz`),
      body.error ? ` (${body.error})` : '');
    drawSpectrogram();
  }

  // Dark blue (quiet) through green and yellow to white (loud): readable in both themes.
  function heat(t) {
    const stops = [[13, 8, 135], [84, 2, 163], [139, 10, 165], [185, 50, 137], [219, 92, 104], [244, 136, 73], [254, 188, 43], [240, 249, 33]];
    const x = Math.max(0, Math.min(1, t)) * (stops.length - 1), i = Math.min(stops.length - 2, Math.floor(x)), f = x - i;
    return stops[i].map((v, k) => Math.round(v + (stops[i + 1][k] - v) * f));
  }

  function drawSpectrogram() {
    const sg = spectrogramView;
    const canvas = $('canvas-spectrogram');
    if (!sg || !canvas) return;
    const c = colors();
    const dpr = window.devicePixelRatio || 1;
    const w = Math.max(50, canvas.clientWidth), h = canvas.clientHeight || 260;
    canvas.width = Math.round(w * dpr); canvas.height = Math.round(h * dpr);
    const g = canvas.getContext('2d');
    g.setTransform(dpr, 0, 0, dpr, 0, 0);
    g.fillStyle = c.bg; g.fillRect(0, 0, w, h);
    const left = 62, right = 70, top = 20, bottom = 20, pw = w - left - right, ph = h - top - bottom;
    const f = sg.frequencies_hz, cols = sg.psd_db, n = cols.length;
    // The colour scale spans the loudest 60 dB, so that the noise floor does not wash it out.
    let hi = -Infinity;
    for (const col of cols) if (col) for (let k = 1; k < col.length; k++) hi = Math.max(hi, col[k]);
    const lo = hi - 60;
    const img = g.createImageData(n, f.length);
    for (let i = 0; i < n; i++) {
      const col = cols[i];
      for (let k = 0; k < f.length; k++) {
        const o = ((f.length - 1 - k) * n + i) * 4;
        if (!col) { img.data[o + 3] = 0; continue; }
        const [r, gg, b] = heat((col[k] - lo) / (hi - lo));
        img.data[o] = r; img.data[o + 1] = gg; img.data[o + 2] = b; img.data[o + 3] = 255;
      }
    }
    const off = document.createElement('canvas');
    off.width = n; off.height = f.length;
    off.getContext('2d').putImageData(img, 0, 0);
    g.imageSmoothingEnabled = false;
    g.drawImage(off, left, top, pw, ph);
    const fMax = f[f.length - 1], t0 = sg.from_ns / 1e6, t1 = t0 + n * sg.column_ns / 1e6;
    g.font = '11px system-ui, sans-serif'; g.fillStyle = c.muted; g.strokeStyle = c.frame;
    const step = [0.1, 0.2, 0.5, 1, 2, 5, 10, 20, 50, 100, 200, 500].find((s) => fMax / s <= 6) || 1000;
    for (let v = 0; v <= fMax + 1e-9; v += step) { const y = top + ph - v / fMax * ph; g.fillText(`${+v.toFixed(2)} Hz`, 4, y + 4); }
    for (let i = 0; i <= 4; i++) { const t = t0 + (t1 - t0) * i / 4; const x = left + pw * i / 4; g.fillText(fmtTime(t).slice(11, 19), Math.min(x, left + pw - 50), h - 6); }
    g.strokeRect(left, top, pw, ph);
    // The colour bar, loud at the top.
    const bx = left + pw + 10;
    for (let y = 0; y < ph; y++) { const [r, gg, b] = heat(1 - y / ph); g.fillStyle = `rgb(${r},${gg},${b})`; g.fillRect(bx, top + y, 12, 1); }
    g.fillStyle = c.muted;
    g.fillText(`${Math.round(hi)} dB`, bx + 15, top + 9);
    g.fillText(`${Math.round(lo)} dB`, bx + 15, top + ph);
    canvas.dataset.drawn = String(n);
    canvas.dataset.peakHz = sg.peak_hz === null ? '' : String(sg.peak_hz);
  }

  function exportMseed() {
    const [fromMs, toMs] = currentWindow();
    const line = $('status-line');
    if ((toMs - fromMs) / 1000 > HISTORY_MAX_SPAN_S) { line.textContent = 'miniSEED export covers at most 1 h of samples: zoom in first.'; return; }
    download(`/api/export.mseed?` + new URLSearchParams({ building: route.building, sensor: route.sensor, from_ns: msToNs(fromMs), to_ns: msToNs(toMs) }), null, null, 'application/vnd.fdsn.mseed');
  }

  // ---- Export ------------------------------------------------------------------------------
  function exportCsv() {
    const [fromMs, toMs] = currentWindow();
    const line = $('status-line');
    if ((toMs - fromMs) / 1000 > HISTORY_MAX_SPAN_S) { line.textContent = 'CSV export covers at most 1 h of samples: zoom in first.'; return; }
    download(`/api/export.csv?` + new URLSearchParams({ building: route.building, sensor: route.sensor, from_ns: msToNs(fromMs), to_ns: msToNs(toMs) }), null);
  }

  // Saves `href` (or `blob`) under `name` through a link kept on the page (#export-link), which
  // also says what was last exported.
  function download(href, name, blob, type) {
    let a = $('export-link');
    if (!a) { a = el('a', { id: 'export-link', hidden: 'hidden' }); document.body.append(a); }
    if (a.dataset.url) URL.revokeObjectURL(a.dataset.url);
    if (blob) { href = URL.createObjectURL(blob); a.dataset.url = href; a.dataset.bytes = String(blob.size); a.dataset.type = blob.type; } else { delete a.dataset.url; a.dataset.bytes = ''; a.dataset.type = type || 'text/csv'; }
    a.href = href;
    if (name) a.setAttribute('download', name); else a.removeAttribute('download');
    a.click();
  }

  const exportName = (ext) => { const [f, t] = currentWindow(); return `${route.building}_${route.sensor || 'building'}_${fmtInput(f).replace(/[: ]/g, '-')}_${Math.round((t - f) / 1000)}s.${ext}`; };

  function exportImage(kind) {
    const canvases = [...document.querySelectorAll('#plot canvas, #bcanvas-overlay, #building-plots canvas, #heli-canvas')].filter((c) => c.offsetParent !== null && c.dataset.plotTop !== undefined);
    if (!canvases.length) { $('status-line').textContent = 'Nothing drawn yet to export.'; return; }
    if (kind === 'png') {
      const out = document.createElement('canvas');
      out.width = Math.max(...canvases.map((c) => c.width)); out.height = canvases.reduce((s, c) => s + c.height, 0);
      const g = out.getContext('2d');
      let y = 0;
      for (const c of canvases) { g.drawImage(c, 0, y); y += c.height; }
      out.toBlob((b) => download(null, exportName('png'), b), 'image/png');
    } else {
      const parts = [];
      let y = 0;
      const W = Math.max(...canvases.map((c) => c.clientWidth));
      for (const c of canvases) {
        const m = c._map;
        if (!m) continue;
        const hh = c.clientHeight;
        parts.push(`<g transform="translate(0,${y})"><rect x="${m.left}" y="${m.top}" width="${m.pw}" height="${m.ph}" fill="none" stroke="#999"/><text x="4" y="14" font-size="12" font-family="sans-serif">${svgText(c.closest('.plot').querySelector('.title').textContent)}</text>`);
        for (const s of m.series) {
          const X = (t) => (m.left + (t - m.x0) / (m.x1 - m.x0) * m.pw).toFixed(1), Y = (v) => (m.top + (m.hi - v) / (m.hi - m.lo) * m.ph).toFixed(1);
          const band = s.points.filter((q) => q.lo !== null && q.hi !== null && Number.isFinite(q.lo));
          if (band.length) parts.push(`<path fill="${s.color}" fill-opacity="0.2" d="M${band.map((q) => `${X(q.t)},${Y(q.hi)}`).join('L')}L${band.slice().reverse().map((q) => `${X(q.t)},${Y(q.lo)}`).join('L')}Z"/>`);
          let d = '';
          for (const q of s.points) { if (q.min === null) continue; d += `${d && !q.gap ? 'L' : 'M'}${X(q.t)},${Y(q.min)}L${X(q.t)},${Y(q.max)}`; }
          parts.push(`<path fill="none" stroke="${s.color}" stroke-width="1" d="${d}"/>`);
        }
        parts.push('</g>');
        y += hh;
      }
      const svg = `<svg xmlns="http://www.w3.org/2000/svg" width="${W}" height="${y}" viewBox="0 0 ${W} ${y}"><rect width="100%" height="100%" fill="#fff"/>${parts.join('')}</svg>`;
      download(null, exportName('svg'), new Blob([svg], { type: 'image/svg+xml' }));
    }
  }
  const svgText = (t) => String(t).replace(/&/g, '&amp;').replace(/</g, '&lt;').replace(/>/g, '&gt;');

  function navigate(change) {
    const r = { ...route, ...change };
    location.hash = sensorHref(r.building, r.sensor, r.at === null ? undefined : r.at, r.span) + (r.at === null ? '' : processingExtra(r));
  }

  // The latest `at` worth reading: its window (three quarters before, one after) ends now.
  const latestAtMs = (spanS) => Date.now() - 0.25 * spanS * 1000;

  function step(dir) {
    const r = route;
    if (r.window && !r.atGiven) { const len = r.window[1] - r.window[0]; navigateWindow(r.window[0] + dir * len, r.window[1] + dir * len); return; }
    const atMs = r.at === null ? Date.now() : r.at / 1e6;
    navigate({ at: msToNs(Math.min(atMs + dir * r.span * 1000, latestAtMs(r.span))) });
  }

  function windowOf(atNs, spanS) {
    const atMs = atNs / 1e6;
    return [atMs - 0.75 * spanS * 1000, atMs + 0.25 * spanS * 1000];
  }

  async function loadHistoryWindow(fromMs, toMs) {
    const q = new URLSearchParams({ building: route.building, sensor: route.sensor, from_ns: msToNs(fromMs), to_ns: msToNs(toMs), width: String(plotWidth()) });
    const myRoute = route;
    const body = await getJson('/api/history?' + q);
    if (route !== myRoute) return;
    historyView = { ...body, fromMs, toMs };
    const v = body.view;
    if (!v) { $('status-line').textContent = `history: ${body.error}`; return; }
    const line = $('status-line');
    if (body.error) line.textContent = `history: ${body.error}`;
    else line.textContent = `history: ${body.batches_read} batches read, ${v.batches} in view` + (v.calibration_versions.length > 1 ? `, calibration versions ${v.calibration_versions.join(', ')} (recalibrated in this range)` : '');
    scheduleDraw();
  }

  async function loadDetail() {
    const myRoute = route;
    const q = new URLSearchParams({ building: route.building, sensor: route.sensor });
    const answer = await getJson('/api/sensor?' + q);
    if (route === myRoute) { detail = answer; renderRecord(); }
  }

  function renderRecord() {
    const box = $('record');
    if (!box) return;
    if (!detail || detail.error) { box.replaceChildren(el('p', { class: 'notice' }, detail ? detail.error : '')); return; }
    const st = detail.status;
    const rec = st.calibration_record;
    if (!st.calibration_version) { box.replaceChildren(el('p', { class: 'warning' }, 'None: the sensor is uncalibrated; its values are raw outputs, not m/s².')); return; }
    if (!rec) { box.replaceChildren(el('p', {}, `Version ${st.calibration_version}; the gateway did not send the record.`)); return; }
    const set = st.mode === 'static' ? 'static' : 'dynamic';
    const dom = (s) => s && s.domain ? `|a| ≤ ${s.domain.amplitude_max_mps2} m/s², ${s.domain.frequency_min_hz}–${s.domain.frequency_max_hz} Hz` : '—';
    const now = Date.now();
    const until = rec.valid_until ? Date.parse(rec.valid_until) : null;
    const untilText = until === null ? 'until superseded' : fmtTime(until);
    const untilNote = until === null ? null : until <= now ? el('span', { class: 'warning' }, ' (expired)') :
      fleet && (until - now) / 86400000 < fleet.expiry_warning_days ? el('span', { class: 'notice' }, ` (expires in ${((until - now) / 86400000).toFixed(1)} days)`) : null;
    const rows = [
      ['Certificate', rec.certificate.id], ['Laboratory', rec.lab.name], ['Accreditation', rec.lab.accreditation],
      ['Approved by', rec.lab.approved_by], ['Version', rec.version], ['Issued', fmtTime(Date.parse(rec.issued_at))],
      ['Valid from', fmtTime(Date.parse(rec.valid_from))], ['Valid until', [untilText, untilNote]],
      ['Mode in use', st.mode], ['Static set domain', dom(rec.static)], ['Dynamic set domain', dom(rec.dynamic)],
      [`Method (${set})`, rec[set] && rec[set].method], [`Reference (${set})`, rec[set] && rec[set].reference],
      ['Coverage factor', rec[set] && rec[set].coverage_factor], ['Sensor', [rec.sensor.model, rec.sensor.serial].filter(Boolean).join(' ') || null],
      ['Output unit', rec.sensor.output_unit], ['Notes', rec.certificate.notes],
    ].filter(([, v]) => v !== undefined && v !== null && v !== '');
    box.replaceChildren(el('dl', { class: 'record' }, rows.map(([k, v]) => [el('dt', {}, k), el('dd', {}, v)])));
  }

  function sensorRow() {
    if (!fleet || !route || route.view !== 'sensor') return null;
    const b = fleet.buildings.find((x) => x.building === route.building);
    if (!b) return null;
    const s = b.sensors.find((x) => x.sensor_id === route.sensor);
    return { b, s: s && sensorOf(b, s) };
  }

  function renderSensorHeader() {
    const box = $('sensor-header');
    if (!box) return;
    const found = sensorRow();
    const items = [];
    if (found) {
      items.push(badge(found.b.state === 'up' ? 'up' : 'down', found.b.state === 'up' ? 'gateway up' : 'gateway DOWN'));
      const f = found.s && found.s.flagged_share;
      if (found.s) items.push(...found.s.states.map((st) => badge(st)), ` last batch ${fmtAge(found.s.last_seen_age_s)}, ${found.s.samples} samples, ${found.s.gaps} gaps`,
        f ? [', ', el('span', { id: 'flagged-share', title: shareTitle(f) }, `${fmtShare(f)} flagged`), f.span_s === null ? ' since the gateway started' : ' in the last minute'] : null);
    }
    const c = (live && live.correction) || (historyView && historyView.view && historyView.view.correction);
    if (c) items.push(` · mode ${c.mode}, calibration ${c.calibration_version ? 'v' + c.calibration_version : 'none'}, k = ${fmtK(c.coverage_factor)}, ${c.sample_rate_hz} Hz`);
    box.replaceChildren(...items.flat().filter((x) => x !== null));
    const list = $('sensor-alerts');
    if (list && fleet) {
      const mine = fleet.alerts.filter((a) => a.building === route.building && a.sensor_id === route.sensor);
      list.replaceChildren(mine.length ? el('table', {}, el('tbody', {}, mine.map((a) => el('tr', { class: 'alert', 'data-level': verified(a) ? a.level : 'unverified', 'data-trust': a.trust },
        el('td', {}, el('a', { href: sensorHref(a.building, a.sensor_id, alertAtNs(a), windowSpan(a)) }, fmtTime(Date.parse(a.at)))),
        el('td', {}, verdict(a)), el('td', {}, a.kind.replace(/_/g, ' ')),
        el('td', { class: 'num' }, a.level === 'stale' ? '—' : `${fmtNum(a.value)} ± ${fmtNum(a.coverage_factor * a.standard_uncertainty, 2)} ${fmtUnit(a.unit)} vs ${fmtNum(a.threshold)}`),
        el('td', { class: 'statement' }, a.statement))))) : el('p', { class: 'meta' }, 'None received since the console started.'));
    }
  }

  function onLive(frame) {
    if (!route || route.view !== 'sensor' || route.window || frame.sensor_id !== route.sensor || frame.building !== route.building) return;
    const v = frame.view;
    if (!live || live.bucket_ns !== v.bucket_ns) live = { bucket_ns: v.bucket_ns, buckets: new Map(), gaps: new Map(), frames: 0 };
    for (const b of v.buckets) live.buckets.set(b[0], b);
    for (const g of v.gaps) live.gaps.set(`${g.start_ns}:${g.cause}`, g);
    live.end_ns = v.end_ns;
    live.span_ns = frame.span_ns;
    live.correction = v.correction || live.correction;
    live.frames += 1;
    live.received_at = Date.now();
    const lo = (v.end_ns - frame.span_ns) / v.bucket_ns - 1;
    for (const k of live.buckets.keys()) if (k < lo) live.buckets.delete(k);
    for (const [k, g] of live.gaps) if (g.end_ns < v.end_ns - frame.span_ns) live.gaps.delete(k);
    const p = $('plot');
    p.dataset.frames = live.frames;
    p.dataset.endNs = String(v.end_ns);
    p.dataset.buckets = live.buckets.size;
    p.dataset.gaps = live.gaps.size;
    $('status-line').textContent = `live: latest sample ${fmtTime(nsToMs(v.end_ns))}` + (frame.malformed ? `, ${frame.malformed} undecodable payloads skipped` : '');
    renderSensorHeader();
    scheduleDraw();
  }

  function onTilt(points) {
    if (!route || route.view !== 'sensor' || !points.length || points[0].sensor_id !== route.sensor) return;
    tilt.push(...points);
    if (tilt.length > 1200) tilt.splice(0, tilt.length - 1200);
    $('plot').dataset.tiltPoints = tilt.length;
    scheduleDraw();
  }

  function scheduleDraw() {
    if (drawPending) return;
    drawPending = true;
    requestAnimationFrame(() => { drawPending = false; drawSensor(); });
  }

  // ---- Plotting ---------------------------------------------------------------------------
  function drawSensor() {
    if (!route || route.view !== 'sensor') return;
    let buckets, gaps, x0, x1, correction, marker = null;
    if (route.window && (route.window[1] - route.window[0]) / 1000 > HISTORY_MAX_SPAN_S) { drawTrend(); return; }
    if (route.window && processing(route)) { drawProcessed(); return; }
    if (!route.window) {
      if (!live) return;
      buckets = [...live.buckets.values()].sort((a, b) => a[0] - b[0]);
      gaps = [...live.gaps.values()];
      x1 = nsToMs(live.end_ns); x0 = x1 - nsToMs(live.span_ns);
      correction = live.correction;
      if (Date.now() - live.received_at > 3000) $('status-line').textContent = `live: no new data for ${((Date.now() - live.received_at) / 1000).toFixed(0)} s (latest sample ${fmtTime(x1)})`;
    } else {
      if (!historyView || !historyView.view) return;
      buckets = historyView.view.buckets; gaps = historyView.view.gaps;
      x0 = historyView.fromMs; x1 = historyView.toMs; correction = historyView.view.correction;
      marker = route.atGiven ? route.at / 1e6 : null;
      $('plot').dataset.buckets = buckets.length;
      $('plot').dataset.gaps = gaps.length;
    }
    const bucketMs = (!route.window ? live.bucket_ns : historyView.view.bucket_ns) / 1e6;
    const overlay = alertOverlay();
    const uncal = correction && correction.mode === 'none';
    let present = 0;
    for (const b of buckets) present |= b[2];
    AXES.forEach((ax, i) => {
      $(`title-${ax}`).textContent = uncal ? `${ax}: raw output, NOT m/s² (uncalibrated)` : `a${ax} (m/s²) with ±k·u`;
      drawSeries($(`canvas-${ax}`), {
        x0, x1, marker, gaps, present, correction, bucketMs, unit: uncal ? '(raw)' : 'm/s²', ...overlay,
        series: [{ name: `a${ax}`, color: AXIS_COLORS[i], points: buckets.map((b) => ({ t: (b[0] + 0.5) * bucketMs, min: b[4 + 2 * i], max: b[5 + 2 * i], lo: b[10 + 2 * i], hi: b[11 + 2 * i], flags: b[2], gap: b[3] === 1 })) }],
      });
    });
    const tp = $('tilt-plot');
    $('freq-plot').hidden = true;
    if (tilt.length && !route.window) {
      tp.hidden = false;
      drawSeries($('canvas-tilt'), {
        x0, x1, marker: null, gaps: [], present: 0,
        series: [['roll', AXIS_COLORS[0]], ['pitch', AXIS_COLORS[1]]].map(([n, color]) => ({
          color, points: tilt.map((t) => { const v = t[`${n}_deg`], u = t.coverage_factor * t[`${n}_uncertainty_deg`]; return { t: nsToMs(t.timestamp_ns), min: v, max: v, lo: v - u, hi: v + u, flags: t.flags, gap: false }; }),
        })),
      });
    } else tp.hidden = true;
    const legend = [el('span', {}, `band: ±k·u, k = ${correction ? fmtK(correction.coverage_factor) : '?'}`), el('i', { style: null, class: 'gap-swatch' }), 'gap'];
    const flagItems = FLAGS.map(([n, c], i) => present & (1 << i) ? [el('i', { 'data-color': c }), n.replace(/_/g, ' ')] : null);
    $('legend').replaceChildren(...legend, ...flagItems.flat().filter(Boolean));
    for (const i of $('legend').querySelectorAll('i[data-color]')) i.style.background = i.dataset.color;
    const gs = $('legend').querySelector('.gap-swatch'); if (gs) gs.style.background = 'rgba(180,35,24,.15)';
  }

  // About n ticks on round values, labelled with one number of decimals for all: the step's.
  // Values are whole multiples of the step (no running sum), so none reads 0.30000000000000004.
  function niceTicks(lo, hi, n) {
    const step0 = (hi - lo) / n;
    const exp = Math.floor(Math.log10(step0));
    const mag = Math.pow(10, exp);
    const mult = [1, 2, 5, 10].find((m) => m * mag >= step0) || 10;
    const step = mult * mag;
    const decimals = Math.max(0, -exp - (mult === 10 ? 1 : 0));
    const out = [];
    for (let i = Math.ceil(lo / step); i * step <= hi; i++) {
      const v = i * step;
      out.push({ v, label: (v === 0 ? 0 : v).toFixed(decimals).replace(/^-(0\.?0*)$/, '$1') });
    }
    return out;
  }

  function drawSeries(canvas, o) {
    const dpr = window.devicePixelRatio || 1;
    const w = Math.max(50, canvas.clientWidth), h = canvas.clientHeight || 170;
    if (canvas.width !== Math.round(w * dpr)) { canvas.width = Math.round(w * dpr); canvas.height = Math.round(h * dpr); }
    const g = canvas.getContext('2d');
    g.setTransform(dpr, 0, 0, dpr, 0, 0);
    const c = colors();
    g.fillStyle = c.bg; g.fillRect(0, 0, w, h);
    const left = 62, right = 8, top = 20, lanes = FLAGS.filter((_, i) => o.present & (1 << i)).length, bottom = 18 + lanes * 4;
    const pw = w - left - right, ph = h - top - bottom;
    let lo = Infinity, hi = -Infinity;
    for (const s of o.series) for (const p of s.points) {
      if (p.t < o.x0 || p.t > o.x1) continue;
      for (const v of [p.min, p.max, p.lo, p.hi]) if (v !== null && Number.isFinite(v)) { lo = Math.min(lo, v); hi = Math.max(hi, v); }
    }
    // The threshold of the alert a link came from, about the mean of the values shown: the
    // alert judges motion above the baseline, which the mean stands for here.
    let thr = null;
    if (o.threshold !== undefined && o.threshold !== null && Number.isFinite(lo)) {
      let sum = 0, n = 0;
      for (const s of o.series) for (const p of s.points) if (p.min !== null && p.t >= o.x0 && p.t <= o.x1) { sum += (p.min + p.max) / 2; n++; }
      if (n) { const mean = sum / n; thr = [mean - o.threshold, mean + o.threshold]; lo = Math.min(lo, thr[0]); hi = Math.max(hi, thr[1]); }
    }
    if (!Number.isFinite(lo)) { lo = -1; hi = 1; }
    if (hi - lo < 1e-6) { lo -= 1e-3; hi += 1e-3; }
    const pad = (hi - lo) * 0.06; lo -= pad; hi += pad;
    const X = (t) => left + (t - o.x0) / (o.x1 - o.x0) * pw;
    const Y = (v) => top + (hi - v) / (hi - lo) * ph;
    canvas._map = { left, top, pw, ph, x0: o.x0, x1: o.x1, lo, hi, series: o.series, correction: o.correction, bucketMs: o.bucketMs, unit: o.unit };
    g.font = '11px system-ui, sans-serif'; g.fillStyle = c.muted; g.strokeStyle = c.grid; g.lineWidth = 1;
    // A label is 11 px tall, centred on its line: one that would rise above the plot area is
    // left out rather than drawn half under the title.
    const ticks = niceTicks(lo, hi, 4).filter((t) => Y(t.v) - 6 >= top);
    for (const t of ticks) { const y = Y(t.v); g.beginPath(); g.moveTo(left, y); g.lineTo(left + pw, y); g.stroke(); g.fillText(t.label, 4, y + 4); }
    canvas.dataset.yTicks = ticks.map((t) => t.label).join(' ');
    canvas.dataset.yTickTop = ticks.length ? String(Math.min(...ticks.map((t) => Y(t.v))) - 6) : '';
    canvas.dataset.plotTop = String(top);
    const spanMs = o.x1 - o.x0;
    const tStep = [100, 200, 500, 1000, 2000, 5000, 10000, 15000, 30000, 60000, 120000, 300000, 600000, 900000, 1800000].find((s) => spanMs / s <= 8) || 3600000;
    for (let t = Math.ceil(o.x0 / tStep) * tStep; t <= o.x1; t += tStep) {
      const x = X(t); g.beginPath(); g.moveTo(x, top); g.lineTo(x, top + ph); g.stroke();
      const label = fmtTick(t, tStep < 1000);
      // Centred under its line, but kept inside the canvas at either end.
      const lw = g.measureText(label).width;
      g.fillText(label, Math.max(2, Math.min(x - lw / 2, w - lw - 2)), h - 4 - lanes * 4);
    }
    // The operators' annotations of this building: a band each, its note written at its top.
    const notes = o.notes !== undefined ? o.notes : notesFor(route && route.sensor);
    let drawnNotes = 0;
    for (const a of notes) {
      const na = nsToMs(a.from_ns), nb = nsToMs(a.to_ns);
      if (nb < o.x0 || na > o.x1) continue;
      const xa = Math.max(left, X(na)), xb = Math.min(left + pw, Math.max(X(nb), xa + 2));
      const event = a.source !== 'operator';
      g.fillStyle = event ? 'rgba(217,119,6,.16)' : 'rgba(105,65,198,.13)';
      g.fillRect(xa, top, xb - xa, ph);
      g.fillStyle = event ? '#b54708' : '#6941c6';
      g.fillRect(xa, top, 2, ph);
      const label = a.text.length > 40 ? a.text.slice(0, 39) + '…' : a.text;
      g.fillText(label, Math.min(xa + 4, left + pw - g.measureText(label).width - 2), top + 12 + 12 * (drawnNotes % 3));
      drawnNotes++;
    }
    canvas.dataset.notes = String(drawnNotes);
    if (o.shade) {
      const a = Math.max(left, X(o.shade[0])), b = Math.min(left + pw, Math.max(X(o.shade[1]), a + 2));
      if (b > a) { g.fillStyle = c.shade; g.fillRect(a, top, b - a, ph); }
      canvas.dataset.shade = `${a.toFixed(0)}-${b.toFixed(0)}`;
    } else delete canvas.dataset.shade;
    g.fillStyle = 'rgba(180,35,24,.15)';
    for (const gap of o.gaps) {
      const a = X(nsToMs(gap.start_ns)), b = Math.max(X(nsToMs(gap.end_ns)), a + 2);
      g.fillRect(a, top, b - a, ph);
    }
    for (const s of o.series) {
      // Band, broken at gaps.
      g.fillStyle = s.color + '33';
      let run = [];
      const flush = () => {
        if (run.length) {
          g.beginPath();
          run.forEach((p, i) => (i ? g.lineTo(X(p.t), Y(p.hi)) : g.moveTo(X(p.t), Y(p.hi))));
          for (let i = run.length - 1; i >= 0; i--) g.lineTo(X(run[i].t), Y(run[i].lo));
          g.closePath(); g.fill();
        }
        run = [];
      };
      for (const p of s.points) {
        if (p.gap || p.lo === null || p.hi === null) flush();
        if (p.lo !== null && p.hi !== null) run.push(p);
      }
      flush();
      // Values: the min/max envelope, broken at gaps.
      g.strokeStyle = s.color; g.lineWidth = 1.2; g.beginPath();
      let prev = null;
      for (const p of s.points) {
        if (p.min === null || p.max === null) { prev = null; continue; }
        const x = X(p.t);
        if (!prev || p.gap) g.moveTo(x, Y(p.min));
        const rising = prev === null || prev <= p.min;
        g.lineTo(x, Y(rising ? p.min : p.max)); g.lineTo(x, Y(rising ? p.max : p.min));
        prev = rising ? p.max : p.min;
      }
      g.stroke();
    }
    // Flag lanes under the plot, one per flag present.
    let lane = 0;
    FLAGS.forEach(([, color], bit) => {
      if (!(o.present & (1 << bit))) return;
      g.fillStyle = color;
      const y = top + ph + 2 + lane * 4;
      for (const s of o.series) for (const p of s.points) if (p.flags & (1 << bit)) g.fillRect(X(p.t) - 1, y, 3, 3);
      lane++;
    });
    if (thr) {
      g.strokeStyle = '#d92d20'; g.setLineDash([6, 4]); g.lineWidth = 1.2;
      for (const v of thr) { g.beginPath(); g.moveTo(left, Y(v)); g.lineTo(left + pw, Y(v)); g.stroke(); }
      g.setLineDash([]); g.fillStyle = '#d92d20'; g.fillText(`threshold ±${fmtNum(o.threshold, 3)} about the mean`, left + 4, Y(thr[1]) - 3);
      canvas.dataset.threshold = thr.map((v) => v.toPrecision(4)).join(' ');
    } else delete canvas.dataset.threshold;
    if (o.marker !== null && o.marker !== undefined) {
      g.strokeStyle = '#b42318'; g.setLineDash([4, 3]); g.beginPath(); g.moveTo(X(o.marker), top); g.lineTo(X(o.marker), top + ph); g.stroke(); g.setLineDash([]);
    }
    g.strokeStyle = c.frame; g.strokeRect(left, top, pw, ph);
  }

  function drawProcessed() {
    if (!processedView) return;
    const v = processedView.view;
    const overlay = alertOverlay();
    AXES.forEach((ax, i) => {
      const p = processedSeries(v, [i], () => `${v.quantity} ${ax}`, [AXIS_COLORS[i]]);
      $(`title-${ax}`).textContent = `${v.quantity} ${ax} (${v.unit}), band ${bandText(v.band)}`;
      drawSeries($(`canvas-${ax}`), { x0: processedView.fromMs, x1: processedView.toMs, marker: null, gaps: p.gaps, present: 0, bucketMs: p.bucketMs, unit: v.unit, shade: overlay.shade, series: p.series });
      $(`canvas-${ax}`).dataset.quantity = v.quantity;
    });
    $('tilt-plot').hidden = true; $('freq-plot').hidden = true;
    $('legend').replaceChildren(el('span', {}, `${v.quantity} in ${bandText(v.band)}; min … max per pixel column; no ±k·u band`));
  }

  // Canvas colours from the page's (light or dark) scheme.
  function colors() {
    const cs = getComputedStyle(document.documentElement);
    const v = (n, d) => (cs.getPropertyValue(n) || d).trim() || d;
    return { bg: v('--plot-bg', '#fff'), muted: v('--muted', '#5f6b76'), grid: v('--grid', '#eef0f3'), frame: v('--line', '#d9dee3'), shade: v('--shade', 'rgba(217,45,32,.12)') };
  }

  // The alert's window and threshold, for plots of the values it judged.
  function alertOverlay() {
    const a = alertInfo;
    if (!a) return {};
    const o = {};
    if (a.window_start_ns != null && a.window_end_ns != null) o.shade = [nsToMs(a.window_start_ns), nsToMs(a.window_end_ns)];
    if (a.kind === 'peak_acceleration' || a.kind === 'rms_acceleration') o.threshold = a.threshold;
    return o;
  }

  // Beyond an hour: per axis the per-minute peak (about the minute's mean) and RMS, and the
  // dominant frequency.
  function drawTrend() {
    if (!trendView || !trendView.minutes) return;
    const { fromMs: x0, toMs: x1 } = trendView;
    const mins = trendView.minutes;
    const half = trendView.minute_ns / 2e6;
    const overlay = alertOverlay();
    let present = 0;
    for (const m of mins) if (m.flagged) present |= 1 << 3;
    AXES.forEach((ax, i) => {
      $(`title-${ax}`).textContent = `a${ax}: per-minute peak |a − mean| (dark) and RMS (light), m/s²`;
      drawSeries($(`canvas-${ax}`), {
        x0, x1, marker: null, gaps: [], present: 0, bucketMs: 60000, unit: 'm/s²', shade: overlay.shade,
        series: [
          { name: `peak a${ax}`, color: AXIS_COLORS[i], points: mins.map((m) => ({ t: nsToMs(m.start_ns) + half, min: m.peak_mps2[i], max: m.peak_mps2[i], lo: null, hi: null, flags: 0, gap: false })) },
          { name: `RMS a${ax}`, color: AXIS_COLORS[i] + '88', points: mins.map((m) => ({ t: nsToMs(m.start_ns) + half, min: m.rms_mps2[i], max: m.rms_mps2[i], lo: null, hi: null, flags: 0, gap: false })) },
        ],
      });
    });
    $('tilt-plot').hidden = true;
    $('freq-plot').hidden = false;
    drawSeries($('canvas-freq'), {
      x0, x1, marker: null, gaps: [], present: 0, bucketMs: 60000, unit: 'Hz',
      series: [{ name: 'dominant', color: '#6941c6', points: mins.filter((m) => m.dominant_hz !== null).map((m) => ({ t: nsToMs(m.start_ns) + half, min: m.dominant_hz, max: m.dominant_hz, lo: null, hi: null, flags: 0, gap: false })) }],
    });
    $('legend').replaceChildren(el('span', {}, `${mins.length} minutes; ${mins.reduce((s, m) => s + m.flagged, 0)} flagged samples`));
    $('plot').dataset.buckets = mins.length;
    void present;
  }

  // ---- A day at a glance: the helicorder -----------------------------------------------------
  // Up to 24 h of one axis in rows (15 min each by default), from the console's per-second
  // minima and maxima (/api/helicorder); gaps shaded grey, flagged seconds ticked in the flag's
  // colour above the trace, annotations shaded.
  let heliView = null;
  let heliGain = 1;
  function renderHelicorder() {
    const r = route;
    heliView = null; currentNotes = [];
    if (!source || source.url.includes('sensor=')) connect('');
    const sensors = buildingSensors();
    const sensor = r.sensor || sensors[0];
    if (!sensor) { $('view').replaceChildren(el('section', { class: 'card' }, el('h2', {}, `Building ${r.building}: day`), el('p', { class: 'notice' }, 'No sensor of this building is known yet.'))); return; }
    const link = (change) => { const x = { ...r, sensor, ...change }; return `#/helicorder/${encodeURIComponent(r.building)}/${encodeURIComponent(x.sensor)}?axis=${x.axis}&hours=${x.hours}&row=${x.row}` + (x.end === null ? '' : `&end=${x.end}`); };
    const sel = (id, values, current, f) => el('select', { id, onchange: (e) => { location.hash = link(f(e.target.value)); } }, values.map(([v, t]) => el('option', { value: v, selected: String(v) === String(current) ? 'selected' : null }, t)));
    const endNs = Number(msToNs(r.window[1]));
    $('view').replaceChildren(el('section', { class: 'card', id: 'helicorder', 'data-building': r.building, 'data-sensor': sensor },
      el('h2', {}, el('a', { href: '#/' }, 'Fleet'), ' / ', el('a', { href: `#/building/${encodeURIComponent(r.building)}` }, r.building), ' / ', el('a', { href: sensorHref(r.building, sensor) }, sensor), ' / day'),
      el('div', { class: 'controls' },
        el('label', {}, 'sensor ', sel('heli-sensor', (sensors.includes(sensor) ? sensors : [sensor, ...sensors]).map((x) => [x, x]), sensor, (v) => ({ sensor: v }))),
        el('label', {}, 'axis ', sel('heli-axis', AXES.map((a) => [a, `a${a}`]), r.axis, (v) => ({ axis: v }))),
        el('label', {}, 'hours ', sel('heli-hours', [1, 2, 6, 12, 24].map((h) => [h, `${h} h`]), r.hours, (v) => ({ hours: Number(v) }))),
        el('label', {}, 'row ', sel('heli-row', [[300, '5 min'], [600, '10 min'], [900, '15 min'], [1800, '30 min'], [3600, '1 h']], r.row, (v) => ({ row: Number(v) }))),
        el('button', { id: 'heli-back', onclick: () => { location.hash = link({ end: endNs - r.hours * 3600e9 }); } }, '◀'),
        el('button', { id: 'heli-now', class: r.end === null ? 'active' : '', onclick: () => { location.hash = link({ end: null }); } }, 'now'),
        el('button', { id: 'heli-fwd', disabled: r.end === null ? 'disabled' : null, onclick: () => { const e = endNs + r.hours * 3600e9; location.hash = link({ end: e >= Date.now() * 1e6 ? null : e }); } }, '▶'),
        el('button', { id: 'heli-gain-down', onclick: () => { heliGain /= 2; drawHelicorder(); } }, 'gain −'),
        el('button', { id: 'heli-gain-up', onclick: () => { heliGain *= 2; drawHelicorder(); } }, 'gain +'),
        el('button', { id: 'btn-png', onclick: () => exportImage('png') }, 'PNG')),
      el('div', { id: 'status-line', class: 'meta' }, `reading ${r.hours} h of a${r.axis}…`),
      el('div', { class: 'plot', id: 'heli-plot' }, el('canvas', { id: 'heli-canvas', width: 1000, height: 700 })),
      el('div', { class: 'legend', id: 'heli-legend' })),
    notesPanel(r.building, sensor));
    loadNotes(r.building, r.window[0], r.window[1]);
    loadHelicorder(r, sensor);
  }

  async function loadHelicorder(r, sensor) {
    const t0 = performance.now();
    // Rows start on whole multiples of their length (15 min: :00, :15, …), as a drum's do.
    const fromMs = Math.floor(r.window[0] / (r.row * 1000)) * r.row * 1000;
    const q = new URLSearchParams({ building: r.building, sensor, axis: r.axis, from_ns: msToNs(fromMs), to_ns: msToNs(r.window[1]), row_s: String(r.row) });
    const body = await getJson('/api/helicorder?' + q);
    if (route !== r) return;
    const fetched = performance.now() - t0;
    if (!body.helicorder) { $('status-line').textContent = `helicorder: ${body.error}`; return; }
    heliView = body;
    const d = drawHelicorder();
    const h = body.helicorder;
    const c = $('heli-canvas');
    c.dataset.fetchMs = fetched.toFixed(0);
    $('status-line').textContent = `a${h.axis} − ${fmtNum(h.mean_mps2, 6)} m/s², ${h.rows} rows of ${fmtSpan(h.row_ns / 1e9)}, one column a second (min … max); ` +
      `${h.gap_seconds} seconds without a sample; read in ${fetched.toFixed(0)} ms (${body.batches_read} batches from the history, the rest from the console's store), drawn in ${d.toFixed(0)} ms` + (body.error ? `; ${body.error}` : '');
  }

  function drawHelicorder() {
    const canvas = $('heli-canvas');
    if (!heliView || !canvas) return 0;
    const t0 = performance.now();
    const h = heliView.helicorder;
    const rowPx = Math.max(8, Math.min(40, Math.floor(760 / h.rows)));
    const top = 8, bottom = 18, left = 70, right = 8;
    canvas.style.height = `${top + bottom + rowPx * h.rows}px`;
    const { g, w, c } = canvasContext(canvas, top + bottom + rowPx * h.rows);
    const pw = w - left - right;
    const sample = [];
    for (const row of h.data) for (let i = 0; i < row.length; i += 17) if (row[i] !== null) sample.push(Math.abs(row[i]));
    sample.sort((a, b) => a - b);
    const amp = Math.max(1, sample[Math.floor(0.99 * (sample.length - 1))] || 1);
    // The 99th percentile of |a − mean| reaches half a row either way: rows do not overlap.
    const k = heliGain * 0.45 * rowPx / amp;
    const colW = pw / h.columns;
    const colors = ['#175cd3', '#b42318', '#1d7a3a', c.muted];
    let gaps = 0, flagged = 0, notes = 0;
    g.textBaseline = 'middle';
    for (let r = 0; r < h.rows; r++) {
      const y0 = top + (r + 0.5) * rowPx;
      const row = h.data[r];
      // Gaps: runs of seconds without a sample.
      g.fillStyle = 'rgba(127,127,127,.18)';
      for (let i = 0; i < h.columns; i++) {
        if (row[2 * i] !== null) continue;
        let j = i; while (j < h.columns && row[2 * j] === null) j++;
        g.fillRect(left + i * colW, y0 - rowPx / 2, (j - i) * colW, rowPx); gaps += j - i; i = j;
      }
      g.strokeStyle = colors[r % colors.length]; g.lineWidth = 1; g.beginPath();
      const clip = (v) => Math.max(y0 - 1.5 * rowPx, Math.min(y0 + 1.5 * rowPx, y0 - v * k));
      for (let i = 0; i < h.columns; i++) {
        const lo = row[2 * i], hi = row[2 * i + 1];
        if (lo === null) continue;
        const x = left + (i + 0.5) * colW;
        g.moveTo(x, clip(hi)); g.lineTo(x, clip(lo) + 0.5);
      }
      g.stroke();
      for (const [col, bits] of h.flags[r]) {
        const bit = FLAGS.findIndex((_, b) => bits & (1 << b));
        g.fillStyle = bit >= 0 ? FLAGS[bit][1] : c.muted;
        g.fillRect(left + col * colW, y0 - rowPx / 2, Math.max(1, colW), 2); flagged++;
      }
      const rowStart = nsToMs(h.from_ns) + r * h.row_ns / 1e6;
      for (const a of notesFor($('helicorder').dataset.sensor)) {
        const a0 = Math.max(nsToMs(a.from_ns), rowStart), a1 = Math.min(nsToMs(a.to_ns), rowStart + h.row_ns / 1e6);
        if (a1 < a0) continue;
        g.fillStyle = a.source === 'operator' ? 'rgba(105,65,198,.2)' : 'rgba(217,119,6,.2)';
        const xa = left + (a0 - rowStart) / (h.row_ns / 1e6) * pw;
        g.fillRect(xa, y0 - rowPx / 2, Math.max(2, (a1 - a0) / (h.row_ns / 1e6) * pw), rowPx); notes++;
      }
      if (rowPx >= 10 || r % Math.ceil(10 / rowPx) === 0) { g.fillStyle = c.muted; g.fillText(fmtTick(rowStart, false).slice(0, 5), 4, y0); }
    }
    g.fillStyle = c.muted; g.textBaseline = 'alphabetic';
    for (let m = 0; m <= 4; m++) { const x = left + pw * m / 4; g.fillText(`+${fmtSpan(Math.round(h.row_ns / 1e9 * m / 4))}`, Math.min(x, w - 50), top + rowPx * h.rows + 14); }
    const ms = performance.now() - t0;
    Object.assign(canvas.dataset, { drawn: '1', rows: String(h.rows), gaps: String(gaps), flagged: String(flagged), notes: String(notes), drawMs: ms.toFixed(1), plotTop: String(top) });
    $('heli-legend').replaceChildren(`${fmtNum(amp * h.scale_mps2 / heliGain / 0.45, 3)} m/s² per ${rowPx} px row height; grey: no sample; ticks above a trace: flagged seconds (`,
      ...FLAGS.filter((_, b) => h.flags.some((f) => f.some(([, bits]) => bits & (1 << b)))).map(([n, col]) => { const i = el('i', {}); i.style.background = col; return [i, n.replace(/_/g, ' ')]; }).flat(), '); purple: annotations.');
    return ms;
  }

  // ---- Annotations: the operators' own marks, on every plot of their building ---------------
  // (PROTOCOL-free: the console's own, /api/annotations). `source` other than `operator` is
  // kept for the event reports' marks, drawn in another colour; the console makes none.
  let currentNotes = [];
  let notesKey = '';
  const notesFor = (sensor) => currentNotes.filter((a) => !a.sensor || !sensor || a.sensor === sensor);
  async function loadNotes(building, fromMs, toMs) {
    const myRoute = route;
    notesKey = `${building}:${fromMs}:${toMs}`;
    const q = new URLSearchParams({ building, from_ns: msToNs(Math.max(0, fromMs)), to_ns: msToNs(toMs) });
    const body = await getJson('/api/annotations?' + q);
    if (route !== myRoute) return;
    currentNotes = body.annotations || [];
    const csv = $('notes-csv');
    if (csv) csv.href = '/api/annotations?' + q + '&format=csv';
    renderNotesList(body.error);
    if (route.view === 'building') drawBuilding(); else if (route.view === 'helicorder') drawHelicorder(); else scheduleDraw();
  }

  function notesPanel(building, sensor) {
    const text = el('input', { id: 'note-text', type: 'text', size: 40, maxlength: 500, placeholder: 'crane lift, sensor moved, …' });
    const from = el('input', { id: 'note-from', type: 'text', size: 19, spellcheck: 'false', placeholder: 'YYYY-MM-DD HH:MM:SS' });
    const to = el('input', { id: 'note-to', type: 'text', size: 19, spellcheck: 'false', placeholder: 'YYYY-MM-DD HH:MM:SS' });
    const only = sensor ? el('input', { id: 'note-sensor-only', type: 'checkbox' }) : null;
    const fill = () => { const [a, b] = route.view === 'sensor' ? currentWindow() : route.window; from.value = fmtInput(a); to.value = fmtInput(b); };
    const add = async () => {
      const status = $('notes-status');
      const a = parseInput(from.value), b = parseInput(to.value);
      if (a === null || b === null) { status.textContent = `from and to are times like ${fmtInput(Date.now())} (${zoneLabel()})`; status.className = 'warning'; return; }
      const body = { building, from_ns: Number(msToNs(a)), to_ns: Number(msToNs(b)), text: text.value };
      if (only && only.checked) body.sensor = sensor;
      let resp, answer;
      try { resp = await fetch('/api/annotations', { method: 'POST', headers: { 'Content-Type': 'application/json' }, body: JSON.stringify(body) }); answer = await resp.text(); } catch (e) { status.textContent = `console unreachable (${e.message || e})`; return; }
      if (!resp.ok) { status.textContent = `console refused (${resp.status}): ${answer.trim()}`; status.className = 'warning'; return; }
      status.className = 'meta'; status.textContent = 'kept'; text.value = '';
      const [wa, wb] = route.view === 'sensor' ? currentWindow() : route.window;
      loadNotes(building, wa, wb);
    };
    setTimeout(fill, 0);
    return el('section', { class: 'card', id: 'notes' }, el('h3', {}, 'Annotations'),
      el('div', { class: 'controls' }, el('label', {}, `from (${zoneLabel()}) `, from), el('label', {}, 'to ', to), el('button', { onclick: fill, title: 'the span shown' }, 'span shown'),
        el('label', {}, 'note ', text), only ? el('label', {}, only, ` ${sensor} only`) : null, el('button', { id: 'note-add', onclick: add }, 'Add'),
        el('a', { id: 'notes-csv', href: '#', download: `${building}_annotations.csv` }, 'CSV')),
      el('div', { id: 'notes-status', class: 'meta' }, me && me.operator ? `shown on every plot of building ${building}` : 'log in to annotate'),
      el('div', { id: 'notes-list' }));
  }

  function renderNotesList(error) {
    const box = $('notes-list');
    if (!box) return;
    if (error) { box.replaceChildren(el('p', { class: 'warning' }, error)); return; }
    box.replaceChildren(currentNotes.length ? el('table', {}, el('tbody', {}, currentNotes.map((a) => el('tr', { class: 'note', 'data-id': a.id, 'data-source': a.source },
      el('td', {}, `${fmtTime(nsToMs(a.from_ns))} – ${fmtTime(nsToMs(a.to_ns))}`), el('td', {}, a.sensor || 'whole building'), el('td', { class: 'statement' }, a.text),
      el('td', {}, a.source === 'operator' ? `by ${a.by}, ${fmtTime(Date.parse(a.at))}` : `from ${a.source}`),
      el('td', {}, me && me.operator && (me.operator.name === a.by || me.operator.role === 'admin') ? el('button', { class: 'note-delete', onclick: async () => {
        const resp = await fetch('/api/annotations/delete', { method: 'POST', headers: { 'Content-Type': 'application/json' }, body: JSON.stringify({ id: a.id }) });
        if (!resp.ok) { $('notes-status').textContent = `console refused (${resp.status}): ${(await resp.text()).trim()}`; return; }
        const [wa, wb] = route.view === 'sensor' ? currentWindow() : route.window; loadNotes(a.building, wa, wb);
      } }, 'Remove') : null))))) : el('p', { class: 'meta' }, 'None in this span.'));
  }

  // ---- Building view: several sensors, time-aligned ----------------------------------------
  let buildingData = null;   // per sensor, its /api/history or /api/trend answer
  function renderBuildingView() {
    const r = route;
    alertInfo = null; buildingData = new Map();
    if (!source || source.url.includes('sensor=')) connect('');
    const [fromMs, toMs] = r.window;
    const spanS = (toMs - fromMs) / 1000;
    const sensors = buildingSensors();
    const base = (change) => { const x = { ...r, ...change }; return `#/building/${encodeURIComponent(r.building)}?from=${msToNs(fromMs)}&to=${msToNs(toMs)}&axis=${x.axis}` + (r.alert ? `&alert=${r.alert}` : '') + processingExtra(x); };
    plotBands = new Map();
    const axisSel = el('select', { id: 'b-axis', onchange: (e) => { location.hash = base({ axis: e.target.value }); } },
      AXES.map((a) => el('option', { value: a, selected: a === r.axis ? 'selected' : null }, `a${a}`)));
    $('view').replaceChildren(el('section', { class: 'card', id: 'building-view', 'data-building': r.building },
      el('h2', {}, el('a', { href: '#/' }, 'Fleet'), ' / building ', r.building),
      el('div', { class: 'controls' },
        el('label', {}, 'axis ', axisSel),
        [[900, '15 min'], [3600, '1 h'], [86400, '24 h'], [604800, '7 d']].map(([n, t]) => el('button', { class: 'last', 'data-last': n, onclick: () => { location.hash = `#/building/${encodeURIComponent(r.building)}?last=${n}&axis=${r.axis}` + (r.alert ? `&alert=${r.alert}` : ''); } }, `last ${t}`)),
        el('label', { title: 'every sensor of these axes in one plot, above the others' }, 'overlay ', AXES.map((a) => [el('input', { type: 'checkbox', class: 'overlay-axis', value: a, checked: r.overlay.includes(a) ? 'checked' : null,
          onchange: () => { location.hash = base({ overlay: [...document.querySelectorAll('input.overlay-axis:checked')].map((c) => c.value).join('') }); } }), a, ' '])),
        el('label', {}, 'show ', el('select', { id: 'b-quantity', onchange: (e) => { location.hash = base({ quantity: e.target.value, band: e.target.value === 'acceleration' ? r.band : (r.band || '0.1-') }); } },
          Object.keys(QUANTITIES).map((q) => el('option', { value: q, selected: q === r.quantity ? 'selected' : null }, q)))),
        el('button', { id: 'btn-png', onclick: () => exportImage('png') }, 'PNG'),
        el('button', { id: 'btn-svg', onclick: () => exportImage('svg') }, 'SVG')),
      r.error ? el('div', { id: 'status-line', class: 'warning' }, `This link cannot be shown: ${r.error}.`) :
        el('div', { id: 'status-line', class: 'meta' }, `${fmtTime(fromMs)} – ${fmtTime(toMs)} (${fmtSpan(Math.round(spanS))}), ${sensors.length} sensors, the same time axis; drag to zoom, Shift-drag to pan.` + (processing(r) ? ` Every plot: ${r.quantity}, band ${r.band} Hz.` : '')),
      r.overlay ? el('div', { class: 'plot', id: 'overlay-plot' }, el('canvas', { id: 'bcanvas-overlay', width: 1000, height: 220 }), el('span', { class: 'title', id: 'overlay-title' }, `overlay: ${sensors.length} sensors, axes ${r.overlay.split('').join(', ')}`), el('div', { class: 'legend', id: 'overlay-legend' })) : null,
      el('div', { id: 'building-plots', 'data-loaded': 0 }, sensors.map((s) => el('div', { class: 'plot', 'data-sensor': s },
        el('div', { class: 'plot-controls' }, el('label', { title: 'this plot only: its band in Hz, LOW-HIGH (Enter); empty: the view\'s' }, 'filter ',
          el('input', { class: 'plot-band', 'data-sensor': s, type: 'text', size: 8, spellcheck: 'false', placeholder: r.band || 'none', onchange: (e) => setPlotBand(r, s, e.target.value.trim(), fromMs, toMs) })), ' Hz'),
        el('canvas', { id: `bcanvas-${s}`, width: 1000, height: 130 }),
        el('span', { class: 'title' }, el('a', { href: `#/sensor/${encodeURIComponent(r.building)}/${encodeURIComponent(s)}?from=${msToNs(fromMs)}&to=${msToNs(toMs)}` + (r.alert ? `&alert=${r.alert}` : '') + processingExtra({ ...r, overlay: '' }) }, s), ` ${r.quantity === 'acceleration' ? 'a' : r.quantity + ' '}${r.axis}`, el('span', { class: 'plot-band-note', 'data-sensor': s }))))),
      el('div', { id: 'readout', hidden: 'hidden' }), el('div', { id: 'selection', hidden: 'hidden' })),
      notesPanel(r.building, null));
    if (r.error) return;
    loadNotes(r.building, fromMs, toMs);
    for (const c of document.querySelectorAll('#building-plots canvas, #bcanvas-overlay')) attachPointer(c, drawBuilding);
    if (r.alert) getJson(`/api/alerts?id=${r.alert}`).then((b) => { if (route === r && b.alerts && b.alerts.length) { alertInfo = b.alerts[0]; drawBuilding(); } });
    loadBuilding(r, sensors, fromMs, toMs);
  }

  // The building's sensors as the fleet view knows them (the gateway's status and alerts).
  function buildingSensors() {
    const b = fleet && fleet.buildings.find((x) => x.building === route.building);
    return b ? b.sensors.map((s) => s.sensor_id) : [];
  }

  // One sensor after the other: the console reads two history views at once at most.
  let plotBands = new Map(); // per sensor of the building view, its own band
  async function loadBuilding(r, sensors, fromMs, toMs) {
    const trend = (toMs - fromMs) / 1000 > HISTORY_MAX_SPAN_S;
    for (const s of sensors) {
      const body = await loadBuildingPlot(r, s, fromMs, toMs, trend);
      if (route !== r) return;
      buildingData.set(s, body);
      $('building-plots').dataset.loaded = buildingData.size;
      drawBuilding();
    }
  }

  async function loadBuildingPlot(r, s, fromMs, toMs, trend) {
    const band = plotBands.get(s) || r.band;
    if (!trend && (band || r.quantity !== 'acceleration')) {
      const body = await getJson(processedQuery(r.building, s, fromMs, toMs, r.quantity, band));
      return { ...body, processed: true };
    }
    const q = new URLSearchParams({ building: r.building, sensor: s, from_ns: msToNs(fromMs), to_ns: msToNs(toMs) });
    if (!trend) q.set('width', String(plotWidth()));
    return getJson((trend ? '/api/trend?' : '/api/history?') + q);
  }

  // One plot's own filter: that plot read again with it.
  async function setPlotBand(r, s, band, fromMs, toMs) {
    if (band && !/^[0-9.]*-[0-9.]*$/.test(band)) { $('status-line').textContent = `"${band}" is not a band LOW-HIGH in Hz`; return; }
    if (band) plotBands.set(s, band); else plotBands.delete(s);
    const body = await loadBuildingPlot(r, s, fromMs, toMs, (toMs - fromMs) / 1000 > HISTORY_MAX_SPAN_S);
    if (route !== r) return;
    if (body.error && !body.view) $('status-line').textContent = `${s}: ${body.error}`;
    buildingData.set(s, body);
    drawBuilding();
  }

  function drawBuilding() {
    if (!route || route.view !== 'building' || !buildingData) return;
    const [x0, x1] = route.window;
    const i = AXES.indexOf(route.axis);
    const overlay = alertOverlay();
    for (const [s, body] of buildingData) {
      const canvas = $(`bcanvas-${s}`);
      if (!canvas) continue;
      // The alert's threshold belongs to its own sensor; its window is shaded on every one.
      const mine = alertInfo && alertInfo.sensor_id === s ? overlay : { shade: overlay.shade };
      const note = document.querySelector(`.plot-band-note[data-sensor="${CSS.escape(s)}"]`);
      if (note) note.textContent = body.processed && body.view ? ` (${body.view.quantity}, ${bandText(body.view.band)}, ${body.view.unit})` : '';
      if (body.processed && body.view) {
        const p = processedSeries(body.view, [i], () => `${body.view.quantity} ${route.axis}`, [AXIS_COLORS[i]]);
        drawSeries(canvas, { x0, x1, marker: null, gaps: p.gaps, present: 0, bucketMs: p.bucketMs, unit: body.view.unit, shade: mine.shade, series: p.series, notes: notesFor(s) });
        canvas.dataset.band = plotBands.get(s) || route.band || '';
      } else if (body.minutes) {
        drawSeries(canvas, { x0, x1, marker: null, gaps: [], present: 0, bucketMs: 60000, unit: 'm/s²', ...mine, threshold: undefined, notes: notesFor(s),
          series: [{ name: `peak a${route.axis}`, color: AXIS_COLORS[i], points: body.minutes.map((m) => ({ t: nsToMs(m.start_ns) + 30000, min: m.peak_mps2[i], max: m.peak_mps2[i], lo: null, hi: null, flags: 0, gap: false })) }] });
      } else if (body.view) {
        const v = body.view, bucketMs = v.bucket_ns / 1e6;
        let present = 0;
        for (const b of v.buckets) present |= b[2];
        drawSeries(canvas, { x0, x1, marker: null, gaps: v.gaps, present, correction: v.correction, bucketMs, unit: 'm/s²', ...mine, notes: notesFor(s),
          series: [{ name: `a${route.axis}`, color: AXIS_COLORS[i], points: v.buckets.map((b) => ({ t: (b[0] + 0.5) * bucketMs, min: b[4 + 2 * i], max: b[5 + 2 * i], lo: b[10 + 2 * i], hi: b[11 + 2 * i], flags: b[2], gap: b[3] === 1 })) }] });
      }
      canvas.dataset.drawn = '1';
    }
    drawOverlay();
  }

  const OVERLAY_COLORS = ['#175cd3', '#1d7a3a', '#9a3412', '#6941c6', '#c11574', '#0e7090', '#b54708', '#475467', '#d92d20', '#079455'];
  // Every sensor's chosen axes in one plot, on the same time axis.
  function drawOverlay() {
    const canvas = $('bcanvas-overlay');
    if (!canvas || !route.overlay) return;
    const [x0, x1] = route.window;
    const series = [];
    const units = new Set();
    let gaps = [], bucketMs = null;
    for (const [s, body] of buildingData) {
      for (const ax of route.overlay) {
        const i = AXES.indexOf(ax);
        const color = OVERLAY_COLORS[series.length % OVERLAY_COLORS.length];
        if (body.processed && body.view) {
          const p = processedSeries(body.view, [i], () => `${s} ${body.view.quantity === 'acceleration' ? 'a' : body.view.quantity + ' '}${ax} (${bandText(body.view.band)})`, [color]);
          series.push(p.series[0]); units.add(body.view.unit); bucketMs = p.bucketMs;
        } else if (body.view) {
          const v = body.view; bucketMs = v.bucket_ns / 1e6; units.add('m/s²');
          series.push({ name: `${s} a${ax}`, color, points: v.buckets.map((b) => ({ t: (b[0] + 0.5) * bucketMs, min: b[4 + 2 * i], max: b[5 + 2 * i], lo: b[10 + 2 * i], hi: b[11 + 2 * i], flags: b[2], gap: b[3] === 1 })) });
        } else if (body.minutes) {
          units.add('m/s²'); bucketMs = 60000;
          series.push({ name: `${s} peak a${ax}`, color, points: body.minutes.map((m) => ({ t: nsToMs(m.start_ns) + 30000, min: m.peak_mps2[i], max: m.peak_mps2[i], lo: null, hi: null, flags: 0, gap: false })) });
        }
      }
    }
    const unit = [...units].join(' / ');
    drawSeries(canvas, { x0, x1, marker: null, gaps, present: 0, bucketMs, unit, shade: alertOverlay().shade, series, notes: notesFor(null) });
    canvas.dataset.series = String(series.length);
    canvas.dataset.drawn = '1';
    const legend = $('overlay-legend');
    legend.replaceChildren(...series.map((x) => [el('i', { 'data-color': x.color }), x.name]).flat(), ...(units.size > 1 ? [el('span', { class: 'warning' }, ' (mixed units: one plot per quantity reads better)')] : []));
    for (const i of legend.querySelectorAll('i[data-color]')) i.style.background = i.dataset.color;
  }

  // ---- Modes view: a building's modal frequencies, damping and shapes (triax-modes) --------
  // Per track (a mode followed across windows) its frequency trend with the stated interval
  // ±k·u as a band and the environmental baseline dashed; the latest window's modes in a table
  // and their shapes as bars with their intervals. From what the console heard on
  // triax/<building>/modes since it started (PROTOCOL.md §3.10).
  let modesView = null;
  const TRACK_COLORS = ['#175cd3', '#1d7a3a', '#9a3412', '#6941c6', '#c11574', '#0e7090', '#b54708', '#475467'];
  const fmtPct = (x) => Number.isFinite(x) ? `${(100 * x).toFixed(2)} %` : '—';
  function renderModes() {
    const r = route;
    modesView = null;
    if (!source || source.url.includes('sensor=')) connect('');
    $('view').replaceChildren(el('section', { class: 'card', id: 'modes-view', 'data-building': r.building },
      el('h2', {}, el('a', { href: '#/' }, 'Fleet'), ' / building ', r.building, ' / modes'),
      el('div', { id: 'modes-status', class: 'meta' }, 'Loading…'),
      el('h3', {}, 'Frequency per track'),
      el('div', { id: 'modes-trends' }),
      el('h3', {}, 'Latest window'),
      el('div', { id: 'modes-latest' }),
      el('div', { id: 'modes-shapes', class: 'shapes' })));
    loadModes(r);
  }

  async function loadModes(r) {
    const body = await getJson('/api/modes?' + new URLSearchParams({ building: r.building }));
    if (route !== r) return;
    if (body.error) { $('modes-status').textContent = body.error; return; }
    const changed = !modesView || modesView.windows !== body.windows || modesView.last_end_ns !== body.last_end_ns;
    modesView = body;
    if (changed) drawModes();
  }

  function drawModes() {
    if (!route || route.view !== 'modes' || !modesView) return;
    const m = modesView;
    const status = $('modes-status');
    status.dataset.windows = m.windows;
    if (!m.windows) {
      status.textContent = 'No modes heard for this building since the console started (triax-modes publishes one window every 30 minutes by default).';
      $('modes-trends').replaceChildren(); $('modes-latest').replaceChildren(); $('modes-shapes').replaceChildren();
      return;
    }
    const refusal = m.last_refusal ? ` Last refused window ${fmtTime(nsToMs(m.last_refusal.start_ns))}: ${m.last_refusal.reason}.` : '';
    status.textContent = `${m.windows} windows heard, ${fmtTime(nsToMs(m.first_start_ns))} – ${fmtTime(nsToMs(m.last_end_ns))}; ${m.tracks.length} tracks.` +
      (m.refused_since_latest ? ` ${m.refused_since_latest} refused since the latest identified one.` : '') + refusal +
      (m.verifying ? (m.unverified ? ` ${m.unverified} windows dropped: not signed by a trusted key.` : '') : ' Not verified: no trusted alerting key is given, so these windows are taken on trust.');
    const x0 = nsToMs(m.first_start_ns), x1 = nsToMs(m.last_end_ns);
    $('modes-trends').replaceChildren(...m.tracks.map((t, i) => {
      const f = t.points[t.points.length - 1];
      return el('div', { class: 'plot', 'data-track': t.track },
        el('canvas', { id: `mcanvas-${t.track}`, class: 'mode-trend', width: 1000, height: 120 }),
        el('span', { class: 'title' }, `track ${t.track} (${t.direction}) ${fmtNum(f.frequency_hz, 5)} Hz ±${fmtNum(f.expanded_hz, 2)}, Hz: the band is ±k·u, dashed the environmental baseline, red a shift`));
    }));
    m.tracks.forEach((t, i) => drawTrack($(`mcanvas-${t.track}`), t, x0, x1, TRACK_COLORS[i % TRACK_COLORS.length]));
    const l = m.latest;
    if (!l) { $('modes-latest').replaceChildren(el('p', { class: 'notice' }, 'Every window heard was refused.')); $('modes-shapes').replaceChildren(); return; }
    $('modes-latest').replaceChildren(
      el('p', { class: 'meta' }, `${fmtTime(nsToMs(l.start_ns))} – ${fmtTime(nsToMs(l.end_ns))}` + (l.temperature_c === null ? '' : `, ${l.temperature_c.toFixed(1)} °C`) + `; intervals at ${Math.round(100 * (l.modes[0] ? l.modes[0].coverage_probability : 0.95))} %.`),
      el('table', { id: 'modes-table' },
        el('thead', {}, el('tr', {}, ['Track', 'Direction', 'Frequency, Hz', 'Damping', 'Verdict'].map((h) => el('th', {}, h)))),
        el('tbody', {}, l.modes.map((md) => el('tr', { 'data-track': md.track ?? '' },
          el('td', {}, md.track ?? '—'), el('td', {}, md.direction),
          el('td', { class: 'num' }, `${fmtNum(md.frequency_hz, 5)} ± ${fmtNum(md.frequency_expanded_hz, 2)}`),
          el('td', { class: 'num' }, `${fmtPct(md.damping_ratio)} ± ${fmtPct(md.damping_expanded)}`),
          el('td', {}, md.verdict ? badge(md.verdict === 'shift' ? 'exceeded' : md.verdict === 'possible' ? 'possible' : 'ok', md.verdict) : '—'))))));
    $('modes-shapes').replaceChildren(...l.modes.map((md, i) => el('div', { class: 'plot shape', 'data-track': md.track ?? '' },
      el('canvas', { id: `shape-${i}`, class: 'mode-shape', width: 480, height: 200 }),
      el('span', { class: 'title' }, `${md.direction} ${fmtNum(md.frequency_hz, 4)} Hz: in-phase amplitude per sensor and direction, ±k·u`))));
    l.modes.forEach((md, i) => drawShape($(`shape-${i}`), md));
  }

  function canvasContext(canvas, hDefault) {
    const dpr = window.devicePixelRatio || 1;
    const w = Math.max(50, canvas.clientWidth), h = canvas.clientHeight || hDefault;
    if (canvas.width !== Math.round(w * dpr)) { canvas.width = Math.round(w * dpr); canvas.height = Math.round(h * dpr); }
    const g = canvas.getContext('2d');
    g.setTransform(dpr, 0, 0, dpr, 0, 0);
    const c = colors();
    g.fillStyle = c.bg; g.fillRect(0, 0, w, h);
    g.font = '11px system-ui, sans-serif';
    return { g, w, h, c };
  }

  function drawTrack(canvas, t, x0, x1, color) {
    if (!canvas) return;
    const { g, w, h, c } = canvasContext(canvas, 120);
    const L = 60, R = 10, T = 20, B = 18;
    const pts = t.points;
    let lo = Infinity, hi = -Infinity;
    for (const p of pts) {
      const e = Number.isFinite(p.expanded_hz) ? p.expanded_hz : 0;
      lo = Math.min(lo, p.frequency_hz - e, p.predicted_hz ?? Infinity); hi = Math.max(hi, p.frequency_hz + e, p.predicted_hz ?? -Infinity);
    }
    if (hi - lo < 1e-6) { lo -= 0.001; hi += 0.001; }
    const pad = 0.08 * (hi - lo); lo -= pad; hi += pad;
    const X = (ms) => L + (w - L - R) * (x1 > x0 ? (ms - x0) / (x1 - x0) : 0.5);
    const Y = (f) => T + (h - T - B) * (hi - f) / (hi - lo);
    g.strokeStyle = c.grid; g.fillStyle = c.muted; g.textAlign = 'right'; g.textBaseline = 'middle';
    for (const tk of niceTicks(lo, hi, 3)) { g.beginPath(); g.moveTo(L, Y(tk.v)); g.lineTo(w - R, Y(tk.v)); g.stroke(); g.fillText(tk.label, L - 4, Y(tk.v)); }
    const mid = (p) => nsToMs(p.start_ns) / 2 + nsToMs(p.end_ns) / 2;
    // The band: each window's interval as a bar, joined where windows follow each other.
    g.fillStyle = color + '33';
    g.beginPath();
    pts.forEach((p, i) => { const x = X(mid(p)), e = Number.isFinite(p.expanded_hz) ? p.expanded_hz : 0; if (i === 0) g.moveTo(x, Y(p.frequency_hz + e)); else g.lineTo(x, Y(p.frequency_hz + e)); });
    for (let i = pts.length - 1; i >= 0; i--) { const p = pts[i], e = Number.isFinite(p.expanded_hz) ? p.expanded_hz : 0; g.lineTo(X(mid(p)), Y(p.frequency_hz - e)); }
    g.closePath(); g.fill();
    for (const p of pts) { const x = X(mid(p)), e = Number.isFinite(p.expanded_hz) ? p.expanded_hz : 0; g.strokeStyle = color + '88'; g.beginPath(); g.moveTo(x, Y(p.frequency_hz - e)); g.lineTo(x, Y(p.frequency_hz + e)); g.stroke(); }
    const withBaseline = pts.filter((p) => p.predicted_hz !== null);
    if (withBaseline.length) {
      g.setLineDash([4, 3]); g.strokeStyle = c.muted; g.beginPath();
      withBaseline.forEach((p, i) => { const x = X(mid(p)), y = Y(p.predicted_hz); if (i === 0) g.moveTo(x, y); else g.lineTo(x, y); });
      g.stroke(); g.setLineDash([]);
    }
    g.strokeStyle = color; g.lineWidth = 1.5; g.beginPath();
    pts.forEach((p, i) => { const x = X(mid(p)), y = Y(p.frequency_hz); if (i === 0) g.moveTo(x, y); else g.lineTo(x, y); });
    g.stroke(); g.lineWidth = 1;
    let shifts = 0;
    for (const p of pts) {
      const shift = p.verdict === 'shift' || p.block_verdict === 'shift';
      shifts += shift ? 1 : 0;
      g.fillStyle = shift ? '#d92d20' : color;
      g.beginPath(); g.arc(X(mid(p)), Y(p.frequency_hz), shift ? 4 : 2, 0, 2 * Math.PI); g.fill();
    }
    g.fillStyle = c.muted; g.textAlign = 'left'; g.textBaseline = 'alphabetic';
    g.fillText(fmtTime(x0), L, h - 4); g.textAlign = 'right'; g.fillText(fmtTime(x1), w - R, h - 4);
    canvas.dataset.points = pts.length; canvas.dataset.shifts = shifts; canvas.dataset.drawn = '1';
  }

  function drawShape(canvas, md) {
    if (!canvas) return;
    const { g, w, h, c } = canvasContext(canvas, 200);
    const L = 36, R = 8, T = 20, B = 42;
    const comps = md.shape;
    let lo = 0, hi = 0;
    for (const s of comps) { const e = Number.isFinite(s.expanded) ? s.expanded : 0; lo = Math.min(lo, s.real - e); hi = Math.max(hi, s.real + e); }
    if (hi - lo < 1e-9) hi = lo + 1;
    const Y = (v) => T + (h - T - B) * (hi - v) / (hi - lo);
    const slot = (w - L - R) / Math.max(1, comps.length);
    g.strokeStyle = c.grid; g.fillStyle = c.muted; g.textAlign = 'right'; g.textBaseline = 'middle';
    for (const tk of niceTicks(lo, hi, 4)) { g.beginPath(); g.moveTo(L, Y(tk.v)); g.lineTo(w - R, Y(tk.v)); g.stroke(); g.fillText(tk.label, L - 3, Y(tk.v)); }
    comps.forEach((s, i) => {
      const x = L + slot * (i + 0.5), bw = Math.max(2, slot * 0.6);
      g.fillStyle = AXIS_COLORS[AXES.indexOf(s.direction)] + (i === md.reference_component ? '' : 'bb');
      const y0 = Y(0), y1 = Y(s.real);
      g.fillRect(x - bw / 2, Math.min(y0, y1), bw, Math.max(1, Math.abs(y1 - y0)));
      if (Number.isFinite(s.expanded) && s.expanded > 0) {
        g.strokeStyle = c.muted; g.beginPath(); g.moveTo(x, Y(s.real - s.expanded)); g.lineTo(x, Y(s.real + s.expanded));
        g.moveTo(x - bw / 4, Y(s.real - s.expanded)); g.lineTo(x + bw / 4, Y(s.real - s.expanded));
        g.moveTo(x - bw / 4, Y(s.real + s.expanded)); g.lineTo(x + bw / 4, Y(s.real + s.expanded)); g.stroke();
      }
      g.save(); g.translate(x, h - B + 4); g.rotate(-Math.PI / 4); g.fillStyle = c.muted; g.textAlign = 'right'; g.textBaseline = 'middle';
      g.fillText(`${s.sensor_id} ${s.direction}`, 0, 0); g.restore();
    });
    canvas.dataset.components = comps.length; canvas.dataset.drawn = '1';
  }

  // ---- Operators: who is logged in, the login form, the time zone choice --------------------
  let me = null;             // /api/me: { operator, login_required, accounts, time_zone }
  async function loadMe() {
    const body = await getJson('/api/me');
    applyMe(body.error ? { operator: null, login_required: false, error: body.error } : body);
  }

  function applyMe(m) {
    me = m;
    siteZone = me.time_zone || null;
    if (tzMode === 'site' && !siteZone) tzMode = 'utc';
    renderWho();
    renderZoneChoice();
  }

  function renderWho() {
    const box = $('who');
    if (!me) { box.replaceChildren(); return; }
    if (me.operator) {
      box.replaceChildren(el('span', { id: 'who-name', 'data-role': me.operator.role }, `${me.operator.name} (${me.operator.role})`), ' ',
        me.operator.via === 'password' ? el('button', { id: 'logout', onclick: logout }, 'Log out') : null);
    } else if (me.login_required || me.accounts) {
      box.replaceChildren(el('a', { id: 'login-link', href: '#/login' }, 'Log in'));
    } else box.replaceChildren(el('span', { class: 'meta', title: 'no operator accounts: triax-console operator add NAME --role operate' }, 'read-only'));
  }

  function renderZoneChoice() {
    const sel = $('tz');
    const opts = [['utc', 'UTC']];
    if (siteZone) opts.push(['site', `site (${siteZone})`]);
    opts.push(['browser', `this browser (${browserZone()})`]);
    sel.replaceChildren(...opts.map(([v, t]) => el('option', { value: v, selected: v === tzMode ? 'selected' : null }, t)));
    sel.onchange = () => { tzMode = sel.value; localStorage.setItem('triax.tz', tzMode); renderZoneChoice(); render(); };
    $('tz-note').textContent = zoneName() === 'UTC' ? 'Times in UTC.' : `Times in ${zoneName()} (${tzMode === 'site' ? "the site's local time" : "this browser's local time"}), labelled with the zone.`;
    document.documentElement.dataset.zone = zoneName();
  }

  let afterLogin = '#/';
  function renderLogin() {
    if (source) { source.close(); source = null; }
    const name = el('input', { id: 'login-name', type: 'text', size: 20, autocomplete: 'username', spellcheck: 'false' });
    const pw = el('input', { id: 'login-password', type: 'password', size: 20, autocomplete: 'current-password' });
    const status = el('div', { id: 'login-status', class: 'meta' }, me && me.login_required ? 'This console shows its fleet to logged-in operators only.' : 'Log in to acknowledge, silence and annotate.');
    const go = async () => {
      let resp, text;
      try {
        resp = await fetch('/api/login', { method: 'POST', headers: { 'Content-Type': 'application/json' }, body: JSON.stringify({ name: name.value.trim(), password: pw.value }) });
        text = await resp.text();
      } catch (e) { status.textContent = `console unreachable (${e.message || e})`; status.className = 'warning'; return; }
      pw.value = '';
      if (!resp.ok) { status.textContent = `console refused (${resp.status}): ${text.trim()}`; status.className = 'warning'; return; }
      await loadMe();
      location.hash = afterLogin === '#/login' ? '#/' : afterLogin;
    };
    for (const i of [name, pw]) i.addEventListener('keydown', (e) => { if (e.key === 'Enter') go(); });
    $('view').replaceChildren(el('section', { class: 'card', id: 'login' }, el('h2', {}, 'Log in'),
      el('div', { class: 'controls' }, el('label', {}, 'operator ', name), el('label', {}, 'password ', pw), el('button', { id: 'login-go', onclick: go }, 'Log in')),
      status));
    name.focus();
  }

  async function logout() {
    try { await fetch('/api/logout', { method: 'POST', headers: { 'Content-Type': 'application/json' }, body: '{}' }); } catch (e) { /* the cookie ends with the console anyway */ }
    await loadMe();
    render();
  }

  // ---- Routing ----------------------------------------------------------------------------
  function render() {
    if (location.hash.startsWith('#/login')) { renderLogin(); return; }
    if (me && me.login_required && !me.operator) { afterLogin = location.hash || '#/'; location.hash = '#/login'; return; }
    route = parseRoute();
    if (route.view === 'sensor') { renderSensor(); return; }
    if (route.view === 'building') { renderBuildingView(); return; }
    if (route.view === 'modes') { renderModes(); return; }
    if (route.view === 'helicorder') { renderHelicorder(); return; }
    if (!source || source.url.includes('sensor=')) connect('');
    if (route.view === 'alerts') renderAlerts(); else { renderFleet(); refreshRows(); }
  }

  // A script error must not pass unseen, leaving a view that looks current.
  const pageError = (what) => { const e = $('page-error'); e.hidden = false; e.textContent = `page error: ${what}; reload the page`; };
  window.addEventListener('error', (e) => pageError(e.message));
  window.addEventListener('unhandledrejection', (e) => pageError(String(e.reason)));
  window.addEventListener('hashchange', render);
  window.addEventListener('resize', () => { scheduleDraw(); drawBuilding(); drawSpectrum(); drawSpectrogram(); drawModes(); if (route && route.view === 'helicorder') drawHelicorder(); });
  setInterval(() => { if (route && route.view === 'sensor' && !route.window) scheduleDraw(); }, 1000);
  // A window of modes comes every half hour or so: a look every 10 s is plenty.
  setInterval(() => { if (route && route.view === 'modes') loadModes(route); }, 10000);
  // The view at once (a console without accounts needs no answer first); once /api/me has
  // answered, the login form if one is needed, or the view again in the site's zone if chosen.
  // Who the page is for comes with it (the server writes it into a meta tag), so that the
  // first view is the right one: the login form when one is needed.
  try {
    const m = document.querySelector('meta[name="triax-me"]');
    if (m && m.content) applyMe(JSON.parse(m.content));
  } catch (e) { /* /api/me below says it again */ }
  render();
  loadMe();
})();
