// Triax console, the page: three views chosen by the URL fragment (#/ fleet, #/alerts,
// #/sensor/<building>/<sensor>[?at=<ns>&span=<s>]), fed by one Server-Sent Events stream and a
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
  const fmtTime = (ms) => Number.isFinite(ms) ? new Date(ms).toISOString().replace('T', ' ').slice(0, 19) + 'Z' : '—';
  const fmtAge = (s) => s === null || s === undefined ? '—' : s < 1 ? 'now' : s < 120 ? `${s.toFixed(0)} s ago` : s < 7200 ? `${(s / 60).toFixed(0)} min ago` : `${(s / 3600).toFixed(1)} h ago`;
  const fmtNum = (x, d = 4) => x === null || x === undefined || !Number.isFinite(x) ? '—' : Number(x).toPrecision(d);
  // A coverage factor to three significant digits, without trailing zeros (2, 1.97).
  const fmtK = (k) => Number.isFinite(k) ? String(Number(Number(k).toPrecision(3))) : '?';
  // Units as the page writes them everywhere (the alerting service sends `m/s^2`).
  const fmtUnit = (u) => String(u ?? '').replace(/\^2/g, '²').replace(/\^3/g, '³');
  const fmtSpan = (s) => s >= 120 && s % 60 === 0 ? `${s / 60} min` : `${s} s`;
  const fmtShare = (f) => !f ? '—' : `${(100 * f.share).toFixed(f.share > 0 && f.share < 0.01 ? 1 : 0)} %`;
  // The time input reads and writes ISO 8601 in UTC, as every other time on the page.
  const fmtInput = (ms) => new Date(ms).toISOString().slice(0, 19).replace('T', ' ');
  const parseInput = (text) => {
    const m = /^\s*(\d{4})-(\d{2})-(\d{2})[ T](\d{2}):(\d{2})(?::(\d{2}))?Z?\s*$/.exec(text);
    if (!m) return null;
    const [y, mo, d, h, mi, se] = m.slice(1).map((x) => Number(x || 0));
    const ms = Date.UTC(y, mo - 1, d, h, mi, se);
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
  let drawPending = false;

  function parseRoute() {
    let h;
    try { h = decodeURI(location.hash || '#/'); } catch (e) { h = '#/'; }
    const [path, query] = h.slice(1).split('?');
    const params = new URLSearchParams(query || '');
    const parts = path.split('/').filter(Boolean);
    if (parts[0] === 'alerts') return { view: 'alerts', params };
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
      return r;
    }
    return { view: 'fleet' };
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
    me.addEventListener('fleet', (e) => { const f = JSON.parse(e.data); if (f) { fleet = f; onFleet(); } });
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

  function onFleet() {
    $('clock').textContent = fmtTime(Date.parse(fleet.now));
    $('alert-count').textContent = fleet.alerts_open ? `(${fleet.alerts_open} open)` : '';
    if (route.view === 'fleet') renderFleet();
    else if (route.view === 'alerts') refreshAlerts();
    else if (route.view === 'sensor') renderSensorHeader();
  }

  // ---- Fleet view -------------------------------------------------------------------------
  function renderFleet() {
    const view = $('view');
    if (!fleet) { view.replaceChildren(el('p', {}, 'Waiting for the console…')); return; }
    const sections = fleet.buildings.map(renderBuilding);
    if (!sections.length) sections.push(el('p', { class: 'notice' }, 'No building heard yet: no gateway has answered a status query or sent a heartbeat.'));
    const extra = [];
    if (fleet.malformed_messages) extra.push(el('p', { class: 'notice' }, `${fleet.malformed_messages} messages skipped (did not decode or contradicted their key).`));
    view.replaceChildren(el('div', { id: 'fleet', 'data-buildings': fleet.buildings.length }, sections, extra));
  }

  function renderBuilding(b) {
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
    const rows = b.sensors.map((s) => renderSensorRow(b, s));
    const table = el('table', {},
      el('thead', {}, el('tr', {}, ['Sensor', 'State', 'Flagged', 'Last seen', 'Samples', 'Gaps (lost)', 'Rejects', 'Mode', 'Calibration', 'Valid until', 'Latest alert'].map((t) => el('th', { title: t === 'Flagged' ? FLAGGED_TITLE : null }, t)))),
      el('tbody', {}, rows));
    const state = b.state === 'up' ? 'up' : b.state === 'down' ? 'down' : 'unknown';
    const listed = b.sensors.filter((s) => s.in_status).length;
    const more = b.total_sensors && b.total_sensors > listed ? el('p', { class: 'meta' }, `Showing ${listed} of ${b.total_sensors} sensors (the first status page).`) : null;
    const worst = b.worst_state;
    return el('section', { class: 'card building', 'data-building': b.building, 'data-state': state, 'data-worst': worst ?? 'none' },
      el('h2', {}, `Building ${b.building} `, worst ? badge(worst, worst.replace(/_/g, ' '), 'the worst state of its sensors') : null,
        badge(state, state === 'up' ? 'gateway up' : state === 'down' ? 'gateway DOWN' : 'no answer')),
      meta, table, more);
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
      el('td', {}, a ? [verdict(a), ' ', a.kind.replace(/_/g, ' '), ' ', el('a', { href: sensorHref(b.building, s.sensor_id, alertAtNs(a), windowSpan(a)) }, fmtTime(Date.parse(a.at)))] : '—'));
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
  const KINDS = ['peak_acceleration', 'rms_acceleration', 'dominant_frequency', 'tilt_change', 'stale'];
  const LEVELS = ['exceeded', 'possible', 'stale', 'unverified'];
  const STATES = ['all', 'open', 'acknowledged', 'silenced'];
  const SINCE = [['', 'any time'], ['3600', 'last 1 h'], ['86400', 'last 24 h'], ['604800', 'last 7 d'], ['2592000', 'last 30 d']];
  let alertsSeen = null;     // fleet counters the alert table was last fetched at
  let alertsFetching = false;
  const operator = () => { const i = $('operator'); return i ? i.value.trim() : ''; };

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
    const who = el('input', { id: 'operator', type: 'text', size: 12, placeholder: 'your name', value: localStorage.getItem('triax.operator') || '' });
    who.addEventListener('change', () => localStorage.setItem('triax.operator', who.value.trim()));
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
        el('label', {}, 'operator ', who),
        el('button', { id: 'ack-selected', onclick: () => acknowledge(checkedIds()) }, 'Acknowledge selected'),
        el('span', { class: 'meta' }, 'silence for ', silenceFor)),
      el('div', { id: 'alerts-status', class: 'meta' }, 'reading the alert log…'),
      el('table', { id: 'alert-table' },
        el('thead', {}, el('tr', {}, ['', 'At', 'Sensor', 'Verdict', 'Kind', 'Value ± k·u', 'Threshold', 'Interval', 'Window', 'Flagged', 'Statement', 'Handled'].map((t) => el('th', {}, t)))),
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
    const [body, silences] = await Promise.all([getJson('/api/alerts?' + q), getJson('/api/silences')]);
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
  }

  function statementCell(text) {
    const first = String(text).split('\n')[0];
    const short = first.length > 90 ? first.slice(0, 89) + '…' : first;
    return el('td', { class: 'statement' }, el('details', {}, el('summary', {}, short), el('div', { class: 'full' }, text)));
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
      el('td', {}, el('input', { type: 'checkbox', class: 'pick', 'aria-label': `select alert ${a.id}` })),
      el('td', {}, fmtTime(Date.parse(a.at))),
      el('td', {}, el('a', { href: sensorHref(a.building, a.sensor_id, alertAtNs(a), windowSpan(a)) + alertLinkExtra(a) }, `${a.building} / ${a.sensor_id}`)),
      el('td', {}, verdict(a), a.late ? badge('late', 'late', 'raised from data recovered from the history') : null),
      el('td', {}, a.kind.replace(/_/g, ' ')),
      el('td', { class: 'num' }, a.level === 'stale' ? '—' : `${fmtNum(a.value)} ± ${fmtNum(k * u, 2)} ${fmtUnit(a.unit)}`),
      el('td', { class: 'num' }, a.level === 'stale' ? '—' : `${fmtNum(a.threshold)} ${fmtUnit(a.unit)}`),
      el('td', { class: 'num' }, a.level === 'stale' ? '—' : `[${fmtNum(a.value - k * u)}, ${fmtNum(a.value + k * u)}]`),
      el('td', { class: 'num' }, `${fmtNum(a.window_s, 3)} s`),
      el('td', { class: 'num' }, `${(100 * a.flagged_fraction).toFixed(0)} %`),
      statementCell(a.statement),
      handledCell(a));
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

  function renderSilences(list) {
    const box = $('silence-list');
    if (!box) return;
    if (!list.length) { box.replaceChildren(el('p', { class: 'meta' }, 'None.')); return; }
    box.replaceChildren(el('table', {}, el('tbody', {}, list.map((s) => el('tr', { class: 'silence', 'data-id': s.id, 'data-active': s.active ? 'true' : 'false' },
      el('td', {}, `#${s.id}`),
      el('td', {}, `${s.building} / ${s.sensor ?? 'every sensor'}, ${s.kind ? s.kind.replace(/_/g, ' ') : 'every kind'}`),
      el('td', {}, `${fmtTime(Date.parse(s.from))} – ${fmtTime(Date.parse(s.until))}`),
      el('td', {}, `by ${s.by}`, s.reason ? ` (${s.reason})` : ''),
      el('td', {}, s.lifted ? `lifted by ${s.lifted.by}, ${fmtTime(Date.parse(s.lifted.at))}` : s.active ? el('button', { class: 'lift', onclick: () => post('/api/alerts/lift', { id: s.id, by: operator() }) }, 'Lift') : 'ended'))))));
  }

  // A write to the alert log; what the console answered is shown, a refusal included.
  async function post(path, body) {
    const status = $('alerts-status');
    if (!operator()) { status.textContent = 'Type your name under "operator" first: acknowledgements and silences record who.'; status.className = 'warning'; $('operator').focus(); return null; }
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
    post('/api/alerts/ack', { ids, by: operator() });
  }

  function silence(a) {
    post('/api/alerts/silence', { building: a.building, sensor: a.sensor_id, kind: a.kind, duration_s: Number($('silence-for').value), by: operator() });
  }

  // ---- Sensor view ------------------------------------------------------------------------
  function plotWidth() {
    return Math.max(50, Math.min(4000, Math.round(($('view').clientWidth || 1000) - 4)));
  }

  function renderSensor() {
    const r = route;
    live = null; tilt = []; historyView = null; detail = null;
    const isLive = r.at === null;
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
        $('status-line').textContent = `"${atInput.value}" is not a time like ${fmtInput(Date.now())} (UTC)`;
      } else navigate({ at: msToNs(ms) });
    };
    atInput.addEventListener('keydown', (e) => { if (e.key === 'Enter') lookBack(); });
    const controls = el('div', { class: 'controls' },
      el('button', { id: 'btn-live', class: isLive ? 'active' : '', onclick: () => navigate({ at: null }) }, 'Live'),
      el('button', { id: 'btn-back', onclick: () => step(-1), title: 'one span back' }, '◀'),
      el('label', {}, 'at (UTC) ', atInput),
      el('button', { id: 'btn-go', onclick: lookBack }, 'Look back'),
      el('button', { id: 'btn-fwd', onclick: () => step(1), title: 'one span forward, up to now', disabled: isLive || atMs >= latestAtMs(spanS) - 1000 ? 'disabled' : null }, '▶'),
      el('label', {}, 'span ', spanSel));
    const plots = el('div', { id: 'plot', 'data-source': r.error ? 'none' : isLive ? 'live' : 'history', 'data-frames': 0, 'data-buckets': 0, 'data-gaps': 0, 'data-tilt-points': 0 },
      AXES.map((ax) => el('div', { class: 'plot' }, el('canvas', { id: `canvas-${ax}`, width: 1000, height: 170 }), el('span', { class: 'title', id: `title-${ax}` }, `a${ax}`))),
      el('div', { class: 'plot', id: 'tilt-plot', hidden: 'hidden' }, el('canvas', { id: 'canvas-tilt', width: 1000, height: 170 }), el('span', { class: 'title' }, 'tilt: roll (blue), pitch (green), degrees, ±k·u shaded')),
      el('div', { class: 'legend', id: 'legend' }));
    $('view').replaceChildren(el('section', { class: 'card', id: 'sensor', 'data-building': r.building, 'data-sensor': r.sensor },
      el('h2', {}, el('a', { href: '#/' }, r.building), ' / ', r.sensor),
      el('div', { id: 'sensor-header', class: 'meta' }),
      controls,
      r.error ? el('div', { id: 'status-line', class: 'warning', 'data-error': 'link' }, `This link cannot be shown: ${r.error}.`)
        : el('div', { id: 'status-line', class: 'meta' }, isLive ? 'waiting for the live stream…' : 'reading the history…'),
      plots),
    el('section', { class: 'card', id: 'calibration' }, el('h3', {}, 'Calibration in force'), el('div', { id: 'record' }, 'asking the gateway…')),
    el('section', { class: 'card' }, el('h3', {}, 'Alerts of this sensor'), el('div', { id: 'sensor-alerts' })));
    renderSensorHeader();
    loadDetail();
    if (r.error) { connect(''); return; }
    const q = new URLSearchParams({ building: r.building, sensor: r.sensor, span_s: String(spanS), width: String(plotWidth()) });
    if (isLive) connect(q.toString());
    else { connect(''); loadHistory(r.at, spanS); }
  }

  function navigate(change) {
    const r = { ...route, ...change };
    location.hash = sensorHref(r.building, r.sensor, r.at === null ? undefined : r.at, r.span);
  }

  // The latest `at` worth reading: its window (three quarters before, one after) ends now.
  const latestAtMs = (spanS) => Date.now() - 0.25 * spanS * 1000;

  function step(dir) {
    const r = route;
    const atMs = r.at === null ? Date.now() : r.at / 1e6;
    navigate({ at: msToNs(Math.min(atMs + dir * r.span * 1000, latestAtMs(r.span))) });
  }

  function windowOf(atNs, spanS) {
    const atMs = atNs / 1e6;
    return [atMs - 0.75 * spanS * 1000, atMs + 0.25 * spanS * 1000];
  }

  async function loadHistory(atNs, spanS) {
    const [fromMs, toMs] = windowOf(atNs, spanS);
    const q = new URLSearchParams({ building: route.building, sensor: route.sensor, from_ns: msToNs(fromMs), to_ns: msToNs(toMs), width: String(plotWidth()) });
    const myRoute = route;
    const body = await getJson('/api/history?' + q);
    if (route !== myRoute) return;
    historyView = { ...body, fromMs, toMs };
    const v = body.view;
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
    return b ? { b, s: b.sensors.find((x) => x.sensor_id === route.sensor) } : null;
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
    if (!route || route.view !== 'sensor' || route.at !== null || frame.sensor_id !== route.sensor || frame.building !== route.building) return;
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
    if (route.at === null) {
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
      marker = route.at / 1e6;
      $('plot').dataset.buckets = buckets.length;
      $('plot').dataset.gaps = gaps.length;
    }
    const bucketMs = (route.at === null ? live.bucket_ns : historyView.view.bucket_ns) / 1e6;
    const uncal = correction && correction.mode === 'none';
    let present = 0;
    for (const b of buckets) present |= b[2];
    AXES.forEach((ax, i) => {
      $(`title-${ax}`).textContent = uncal ? `${ax}: raw output, NOT m/s² (uncalibrated)` : `a${ax} (m/s²) with ±k·u`;
      drawSeries($(`canvas-${ax}`), {
        x0, x1, marker, gaps, present,
        series: [{ color: AXIS_COLORS[i], points: buckets.map((b) => ({ t: (b[0] + 0.5) * bucketMs, min: b[4 + 2 * i], max: b[5 + 2 * i], lo: b[10 + 2 * i], hi: b[11 + 2 * i], flags: b[2], gap: b[3] === 1 })) }],
      });
    });
    const tp = $('tilt-plot');
    if (tilt.length && route.at === null) {
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
    g.clearRect(0, 0, w, h);
    const left = 62, right = 8, top = 20, lanes = FLAGS.filter((_, i) => o.present & (1 << i)).length, bottom = 18 + lanes * 4;
    const pw = w - left - right, ph = h - top - bottom;
    let lo = Infinity, hi = -Infinity;
    for (const s of o.series) for (const p of s.points) {
      if (p.t < o.x0 || p.t > o.x1) continue;
      for (const v of [p.min, p.max, p.lo, p.hi]) if (v !== null && Number.isFinite(v)) { lo = Math.min(lo, v); hi = Math.max(hi, v); }
    }
    if (!Number.isFinite(lo)) { lo = -1; hi = 1; }
    if (hi - lo < 1e-6) { lo -= 1e-3; hi += 1e-3; }
    const pad = (hi - lo) * 0.06; lo -= pad; hi += pad;
    const X = (t) => left + (t - o.x0) / (o.x1 - o.x0) * pw;
    const Y = (v) => top + (hi - v) / (hi - lo) * ph;
    g.font = '11px system-ui, sans-serif'; g.fillStyle = '#5f6b76'; g.strokeStyle = '#eef0f3'; g.lineWidth = 1;
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
      const d = new Date(t).toISOString();
      const label = tStep < 1000 ? d.slice(14, 23) : d.slice(11, 19);
      // Centred under its line, but kept inside the canvas at either end.
      const lw = g.measureText(label).width;
      g.fillText(label, Math.max(2, Math.min(x - lw / 2, w - lw - 2)), h - 4 - lanes * 4);
    }
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
    if (o.marker !== null) {
      g.strokeStyle = '#b42318'; g.setLineDash([4, 3]); g.beginPath(); g.moveTo(X(o.marker), top); g.lineTo(X(o.marker), top + ph); g.stroke(); g.setLineDash([]);
    }
    g.strokeStyle = '#d9dee3'; g.strokeRect(left, top, pw, ph);
  }

  // ---- Routing ----------------------------------------------------------------------------
  function render() {
    route = parseRoute();
    if (route.view === 'sensor') { renderSensor(); return; }
    if (!source || source.url.includes('sensor=')) connect('');
    if (route.view === 'alerts') renderAlerts(); else renderFleet();
  }

  // A script error must not pass unseen, leaving a view that looks current.
  const pageError = (what) => { const e = $('page-error'); e.hidden = false; e.textContent = `page error: ${what}; reload the page`; };
  window.addEventListener('error', (e) => pageError(e.message));
  window.addEventListener('unhandledrejection', (e) => pageError(String(e.reason)));
  window.addEventListener('hashchange', render);
  window.addEventListener('resize', () => scheduleDraw());
  setInterval(() => { if (route && route.view === 'sensor' && route.at === null) scheduleDraw(); }, 1000);
  render();
})();
