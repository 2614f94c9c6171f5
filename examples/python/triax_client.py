#!/usr/bin/env python3
"""A Triax client in Python, written from PROTOCOL.md alone.

Three commands:

  subscribe  decode a building's corrected batches (PROTOCOL.md §2.2) and print every sample
             with its expanded uncertainty (k·u) and quality flags (§2.3);
  follow     the same, losing nothing (PROTOCOL.md §5.2): sequence gaps and the heartbeat are
             filled from the gateway's history, and with --out FILE the batches go to FILE as
             JSON lines, from which a restarted `follow --out FILE` resumes where it stopped,
             exactly once;
  simulate   publish raw batches (§2.1) for one sensor, as a sensor node would: a sine on x and
             gravity on z, turned into outputs through a diagonal gain and offset;
  alerts     print a building's alerts (§3.6), each with how far it can be trusted: `verified`
             only when signed by an alerting key given with --trusted-alert-key (the service's
             signing_key_file.pub); `unknown_key`, `bad_signature` or `unsigned` otherwise,
             and then never as a verdict.

Requires `eclipse-zenoh` (see requirements.txt) and the standard library; `alerts` also
`cryptography`, for Ed25519.

  python3 triax_client.py subscribe --building hq
  python3 triax_client.py simulate --building hq --sensor py-01 --count 100
  python3 triax_client.py subscribe --building hq --connect tcp/127.0.0.1:7447 --no-multicast
  python3 triax_client.py follow --building hq --out hq.jsonl   # kill it, start it again: no loss

With --json, each batch is one JSON object on a line (non-finite numbers as null), for other
programs to read.
"""

import argparse
import json
import math
import re
import struct
import sys
import time

import zenoh

# --- Keys (PROTOCOL.md §1) ------------------------------------------------------------------

ROOT = "triax"
ID_RE = re.compile(r"^[A-Za-z0-9_-]{1,64}$")


def check_id(kind, value):
    # Ids can never add a chunk or a wildcard to a key: refuse anything else before using it.
    if not ID_RE.match(value):
        raise ValueError(f"{kind} id {value!r}: 1 to 64 characters from A-Z a-z 0-9 _ -")
    return value


def raw_key(building, sensor):
    return f"{ROOT}/{check_id('building', building)}/raw/{check_id('sensor', sensor)}"


def corrected_key(building, sensor=None):
    # No sensor: every sensor of the building, the `*` wildcard of one chunk.
    s = "*" if sensor is None else check_id("sensor", sensor)
    return f"{ROOT}/{check_id('building', building)}/corrected/{s}"


# --- Binary batches (PROTOCOL.md §2) --------------------------------------------------------

MAGIC = b"TX"
KIND_RAW = 1
KIND_CORRECTED = 2
FORMAT_VERSION = 1
MAX_SAMPLES = 16384
RAW_HAS_TEMPERATURE = 0x0001
FLAGS_ALL = 0x07FF  # the bits defined in this version; readers keep others (PROTOCOL.md §4)
FLAG_NAMES = [
    "uncalibrated",
    "calibration_expired",
    "outside_amplitude",
    "outside_frequency",
    "sequence_gap",
    "non_finite_input",
    "clipped",
    "duplicate",
    "outside_temperature",
    "calibration_suspect",
    "late",
]
MODES = {0: "none", 1: "static", 2: "dynamic", 3: "split"}
CORRECTED_SAMPLE = struct.Struct("<6fH")  # ax ay az ux uy uz flags: 26 bytes


class DecodeError(ValueError):
    pass


def flag_names(bits):
    return [name for i, name in enumerate(FLAG_NAMES) if bits & (1 << i)]


def prefix_len(id_len):
    return 35 + id_len


def encode_prefix(kind, flags, sensor, sequence, timestamp_ns, sample_rate_hz, n):
    sid = check_id("sensor", sensor).encode("ascii")
    return (
        MAGIC
        + struct.pack("<BBHB", kind, FORMAT_VERSION, flags, len(sid))
        + sid
        + struct.pack("<QqdI", sequence, timestamp_ns, sample_rate_hz, n)
    )


def decode_prefix(payload, expected_kind):
    """Returns (header dict, flags, n, offset after the prefix); refuses what §2 refuses."""
    if len(payload) < 7:
        raise DecodeError(f"payload is {len(payload)} bytes: too short for a header")
    if payload[0:2] != MAGIC:
        raise DecodeError(f"bad magic {payload[0:2].hex()}")
    kind, version, flags, id_len = struct.unpack_from("<BBHB", payload, 2)
    if kind != expected_kind:
        raise DecodeError(f"message kind {kind} where {expected_kind} was expected")
    if version != FORMAT_VERSION:
        raise DecodeError(f"format version {version} is not supported")
    if not 1 <= id_len <= 64:
        raise DecodeError(f"sensor id length {id_len} is outside 1..=64")
    if len(payload) < prefix_len(id_len):
        raise DecodeError(f"payload is {len(payload)} bytes: too short for a header")
    try:
        sensor = check_id("sensor", payload[7 : 7 + id_len].decode("ascii"))
    except (UnicodeDecodeError, ValueError) as e:
        raise DecodeError(f"bad sensor id: {e}") from None
    sequence, timestamp_ns, sample_rate_hz, n = struct.unpack_from("<QqdI", payload, 7 + id_len)
    if not (math.isfinite(sample_rate_hz) and sample_rate_hz > 0):
        raise DecodeError(f"sample rate {sample_rate_hz} is not finite and positive")
    if not 1 <= n <= MAX_SAMPLES:
        raise DecodeError(f"sample count {n} is outside 1..={MAX_SAMPLES}")
    header = {
        "sensor_id": sensor,
        "sequence": sequence,
        "timestamp_ns": timestamp_ns,
        "sample_rate_hz": sample_rate_hz,
    }
    return header, flags, n, prefix_len(id_len)


def encode_raw(sensor, sequence, timestamp_ns, sample_rate_hz, samples, temperature_c=None):
    """A raw batch (§2.1); `samples` are (vx, vy, vz) outputs in the sensor's output unit."""
    n = len(samples)
    if not 1 <= n <= MAX_SAMPLES:
        raise ValueError(f"a raw batch holds 1..={MAX_SAMPLES} samples, not {n}")
    flags = RAW_HAS_TEMPERATURE if temperature_c is not None else 0
    out = bytearray(encode_prefix(KIND_RAW, flags, sensor, sequence, timestamp_ns, sample_rate_hz, n))
    if temperature_c is not None:
        out += struct.pack("<f", temperature_c)
    for v in samples:
        out += struct.pack("<3f", *v)
    return bytes(out)


def decode_corrected(payload):
    """A corrected batch (§2.2) as a dict; raises DecodeError for anything §2 refuses."""
    payload = bytes(payload)
    # Flags defined after this reader are kept (any flag means "not clean", PROTOCOL.md §4).
    header, batch_flags, n, off = decode_prefix(payload, KIND_CORRECTED)
    expected = off + 14 + CORRECTED_SAMPLE.size * n
    if len(payload) != expected:
        raise DecodeError(f"{n} samples need {expected} bytes, the payload has {len(payload)}")
    calibration_version, mode, _reserved, k = struct.unpack_from("<QBBf", payload, off)
    if mode not in MODES:
        raise DecodeError(f"unknown correction mode {mode}")
    if not (math.isfinite(k) and k > 0):
        raise DecodeError(f"coverage factor {k} is not finite and positive")
    samples = []
    for i in range(n):
        ax, ay, az, ux, uy, uz, flags = CORRECTED_SAMPLE.unpack_from(payload, off + 14 + 26 * i)
        samples.append({"accel_mps2": [ax, ay, az], "uncertainty_mps2": [ux, uy, uz], "flags": flags})
    return {
        **header,
        "batch_flags": batch_flags,
        "calibration_version": calibration_version,
        "mode": MODES[mode],
        "coverage_factor": k,
        "samples": samples,
    }


# --- Zenoh -------------------------------------------------------------------------------------


def open_session(args):
    conf = zenoh.Config()
    conf.insert_json5("mode", json.dumps(args.mode))
    if args.connect:
        conf.insert_json5("connect/endpoints", json.dumps(args.connect))
    if args.listen:
        conf.insert_json5("listen/endpoints", json.dumps(args.listen))
    if args.no_multicast:
        conf.insert_json5("scouting/multicast/enabled", "false")
    return zenoh.open(conf)


def finite_or_none(x):
    # JSON has no NaN: an uncalibrated sample's uncertainty travels as null.
    return x if math.isfinite(x) else None


def batch_json(key, batch):
    out = dict(batch, key=key)
    out["samples"] = [
        {
            "accel_mps2": [finite_or_none(a) for a in s["accel_mps2"]],
            "uncertainty_mps2": [finite_or_none(u) for u in s["uncertainty_mps2"]],
            "flags": s["flags"],
        }
        for s in batch["samples"]
    ]
    return json.dumps(out)


def print_batch(key, b):
    names = ",".join(flag_names(b["batch_flags"])) or "none"
    print(
        f"{key} seq={b['sequence']} n={len(b['samples'])} rate={b['sample_rate_hz']} Hz "
        f"calibration v{b['calibration_version']} ({b['mode']}) k={b['coverage_factor']} "
        f"flags={names}"
    )
    k = b["coverage_factor"]
    dt_ns = 1e9 / b["sample_rate_hz"]
    for i, s in enumerate(b["samples"]):
        t_ns = b["timestamp_ns"] + round(i * dt_ns)
        if s["flags"] & 0x0001:
            # Uncalibrated: raw outputs passed through, not m/s², and no uncertainty.
            axes = "  ".join(f"{a:.4f}" for a in s["accel_mps2"]) + " (raw output, not m/s^2)"
        else:
            axes = "  ".join(
                f"{a:+.4f} ± {k * u:.4f}" for a, u in zip(s["accel_mps2"], s["uncertainty_mps2"])
            ) + " m/s^2 (± k·u)"
        extra = ",".join(flag_names(s["flags"]))
        print(f"  {t_ns}  {axes}" + (f"  [{extra}]" if extra else ""))
    sys.stdout.flush()


def cmd_subscribe(args):
    session = open_session(args)
    key_expr = corrected_key(args.building, args.sensor)
    sub = session.declare_subscriber(key_expr)
    if args.json:
        print(json.dumps({"event": "ready", "key_expr": key_expr}), flush=True)
    else:
        print(f"listening on {key_expr}", file=sys.stderr, flush=True)
    received = 0
    deadline = time.monotonic() + args.timeout_s if args.timeout_s else None
    try:
        while args.count == 0 or received < args.count:
            sample = sub.try_recv()
            if sample is None:
                if deadline is not None and time.monotonic() > deadline:
                    print(f"timeout after {received} batch(es)", file=sys.stderr)
                    return 1
                time.sleep(0.005)
                continue
            key = str(sample.key_expr)
            try:
                batch = decode_corrected(sample.payload.to_bytes())
            except DecodeError as e:
                print(f"{key}: refused: {e}", file=sys.stderr)
                continue
            received += 1
            if args.json:
                print(batch_json(key, batch), flush=True)
            else:
                print_batch(key, batch)
    except KeyboardInterrupt:
        pass
    finally:
        sub.undeclare()
        session.close()
    return 0


# --- History and losing nothing (PROTOCOL.md §5) -----------------------------------------------

HISTORY_PAGE = 10000
FLAG_DUPLICATE = 0x0080
FLAG_LATE = 0x0400
# Live batches and heartbeats a follower holds while it reads the history or writes its output.
LIVE_QUEUE = 4096
# Holes remembered per sensor (§5.2 step 6).
MAX_HOLES = 64
BEATS_QUEUE = 64


def history_key(building, sensor):
    return f"{ROOT}/{check_id('building', building)}/history/{check_id('sensor', sensor)}"


def fetch_history(session, building, sensor, from_seq=None, to_seq=None, timeout_s=10.0,
                  from_ns=None, to_ns=None):
    """Every kept batch of `sensor` with a sequence number in [from_seq, to_seq] and a first
    sample in [from_ns, to_ns), page by page, as (payload bytes, decoded batch), in the order the
    gateway received them."""
    params = [f"limit={HISTORY_PAGE}"]
    for name, value in [("from_seq", from_seq), ("to_seq", to_seq), ("from_ns", from_ns),
                        ("to_ns", to_ns)]:
        if value is not None:
            params.append(f"{name}={value}")
    out = []
    after = None
    while True:
        page = params + ([f"after={after}"] if after else [])
        selector = f"{history_key(building, sensor)}?{';'.join(page)}"
        replies = session.get(
            selector, consolidation=zenoh.ConsolidationMode.NONE, timeout=timeout_s
        )
        n = 0
        for reply in replies:
            if reply.ok is None:
                raise RuntimeError(f"history query {selector}: {reply.err.payload.to_bytes().decode()}")
            payload = reply.ok.payload.to_bytes()
            out.append((payload, decode_corrected(payload)))
            if reply.ok.attachment is not None:
                after = reply.ok.attachment.to_bytes().decode()
            n += 1
        # Zenoh also ends a query, with no error, when its link closes mid-answer: only an
        # empty page after the last cursor proves the end (PROTOCOL.md §5.1).
        if n == 0 or after is None:
            return out


def is_duplicate(batch):
    return bool(batch["batch_flags"] & FLAG_DUPLICATE)


def is_late(batch):
    """Fetched by the gateway from the node's buffer after later batches (§2.3, §5.4)."""
    return bool(batch["batch_flags"] & FLAG_LATE)


def position(batch):
    """Where a sensor's stream is left after `batch`: (sequence, timestamp_ns). The time orders
    a sensor's batches across restarts of its node, where sequence numbers start again."""
    return batch["sequence"], batch["timestamp_ns"]


def duration_ns(batch):
    return int(len(batch["samples"]) * 1e9 / batch["sample_rate_hz"])


class Follower:
    """A building's corrected batches, none lost that the history holds (PROTOCOL.md §5.2).

    Per sensor it keeps a mark: the position of the last batch handed over (duplicates aside)
    and where that batch ended. The history is always asked by time, never by sequence number
    alone, since a restarted node numbers a new run from 0 again. Batches flagged `late` fill the
    holes the numbering showed (§5.2 step 6): per sensor it remembers them, at most MAX_HOLES."""

    def __init__(self, session, building, resume=None, new_sensors_from_ns=None, holes=None):
        self.session = session
        self.building = building
        # sensor -> (sequence, timestamp_ns, end_ns) of the last batch handed over.
        self.marks = {s: (seq, ts, ts) for s, (seq, ts) in (resume or {}).items()}
        # A sensor never seen is followed from here on (by the node's clock).
        self.new_from_ns = time.time_ns() if new_sensors_from_ns is None else new_sensors_from_ns
        # The last heartbeat number seen, per gateway.
        self.beats = {}
        # Zenoh's receive thread must never wait for us: the history's replies come on the same
        # link, behind the live batches, and a full queue that blocks it holds them back until
        # the query times out. A full queue drops its oldest instead; the next batch or
        # heartbeat shows what is missing, and the history has it.
        self.live = session.declare_subscriber(
            corrected_key(building), zenoh.handlers.RingChannel(LIVE_QUEUE))
        self.beats_sub = session.declare_subscriber(
            f"{ROOT}/{check_id('building', building)}/heartbeat", zenoh.handlers.RingChannel(BEATS_QUEUE))
        self.ready = []
        self.recovered = 0
        self.late = 0
        # sensor -> list of [after, before] positions around batches still missing; saved ones
        # first: late batches kept in them while we were away come from the history.
        self.holes = {s: [list(h) for h in hs] for s, hs in (holes or {}).items() if hs}
        for sensor, hs in list(self.holes.items()):
            for hole in [list(h) for h in hs]:
                now = self.hole_of(sensor, hole[1][1] - 1)
                if now is not None:
                    self.fill_hole(sensor, now, before=now[1])
        for sensor, mark in list(self.marks.items()):
            self.recover(sensor, mark[1] + 1)

    def recover(self, sensor, from_ns, through=None, before=None):
        """Hands over the kept batches of `sensor` from `from_ns` on, after its mark: up to and
        including position `through`, or up to position `before` (a live batch the caller hands
        over itself), or all. Duplicates stay out: repeats of what was handed over."""
        target = through or before
        to_ns = None if target is None else target[1] + 1
        got = fetch_history(self.session, self.building, sensor, from_ns=from_ns, to_ns=to_ns)
        # Late batches are kept after later ones: in time order each fits where it belongs.
        got.sort(key=lambda pb: pb[1]["timestamp_ns"])
        for payload, b in got:
            if is_duplicate(b):
                continue
            p = position(b)
            if before is not None and p == before:
                break
            mark = self.marks.get(sensor)
            if mark is None or p[1] > mark[1]:
                self.recovered += 1
                self.hand_over(payload, b)
            if through is not None and p == through:
                break

    def hand_over(self, payload, batch):
        sensor = batch["sensor_id"]
        mark = self.marks.get(sensor)
        p = position(batch)
        if is_late(batch):
            self.late += 1
        if is_late(batch) and mark is not None and p[1] <= mark[1]:
            self.fill(sensor, p)
        elif not is_duplicate(batch):
            if mark is not None and p[0] > mark[0] + 1 and p[1] > mark[1]:
                holes = self.holes.setdefault(sensor, [])
                if len(holes) >= MAX_HOLES:
                    holes.pop(0)
                holes.append([mark[:2], p])
            elif mark is None and p[0] > 0 and p[1] > self.new_from_ns and not is_late(batch):
                # Met for the first time past its number 0: its earlier batches (from the time
                # it is followed from) may still come late from the node's buffer.
                self.holes[sensor] = [[(-1, self.new_from_ns - 1), p]]
            self.marks[sensor] = (*p, batch["timestamp_ns"] + duration_ns(batch))
        self.ready.append((payload, batch))

    def hole_of(self, sensor, ts):
        for hole in self.holes.get(sensor, []):
            if hole[0][1] < ts < hole[1][1]:
                return hole
        return None

    def fill(self, sensor, p):
        """A late batch handed over: its hole now starts after it, and is gone once full."""
        hole = self.hole_of(sensor, p[1])
        if hole is not None:
            hole[0] = p
            if hole[1][0] <= p[0] + 1:
                self.holes[sensor].remove(hole)

    def fill_hole(self, sensor, hole, through=None, before=None):
        """Hands over the late batches the history holds inside `hole`, up to a position."""
        target = through or before
        for payload, b in sorted(
                fetch_history(self.session, self.building, sensor, from_ns=hole[0][1] + 1,
                              to_ns=target[1] + 1),
                key=lambda pb: pb[1]["timestamp_ns"]):
            p = position(b)
            if before is not None and p == before:
                break
            if is_late(b) and self.hole_of(sensor, p[1]) is not None:
                self.recovered += 1
                self.hand_over(payload, b)
            if through is not None and p == through:
                break

    def on_late(self, payload, batch):
        sensor = batch["sensor_id"]
        p = position(batch)
        hole = self.hole_of(sensor, p[1])
        if hole is None:
            return  # one we have
        if p[0] != hole[0][0] + 1:
            self.fill_hole(sensor, hole, before=p)  # late batches lost before it
        if self.hole_of(sensor, p[1]) is not None:
            self.hand_over(payload, batch)

    def on_live(self, payload):
        batch = decode_corrected(payload)
        sensor = batch["sensor_id"]
        seq, ts = position(batch)
        mark = self.marks.get(sensor)
        # Behind the position, or, for a sensor not met yet, before it is followed from.
        if is_late(batch) and (ts <= mark[1] if mark is not None else ts < self.new_from_ns):
            self.on_late(payload, batch)
            return
        # A late batch ahead of the position overtook (or outlived) the live batch that would
        # have shown its hole: taken in line as a live batch is.
        if is_duplicate(batch):
            self.hand_over(payload, batch)  # a repeat, passed on as the live stream carries it
            return
        mark = self.marks.get(sensor)
        if mark is None:
            # Room for a whole batch since we started: its first batches may have been lost.
            if ts - self.new_from_ns >= max(duration_ns(batch), 1):
                self.recover(sensor, self.new_from_ns, before=(seq, ts))
        elif ts <= mark[1]:
            return  # already handed over from the history
        elif not (seq == mark[0] + 1 and ts - mark[2] < max(duration_ns(batch), 1)):
            # Not next in line by number and time: a gap, or a restarted node's new run.
            self.recover(sensor, mark[1] + 1, before=(seq, ts))
        mark = self.marks.get(sensor)
        if mark is None or ts > mark[1]:
            self.hand_over(payload, batch)

    def on_heartbeat(self, payload):
        beat = json.loads(payload)
        if beat.get("format_version") != 1:
            return
        previous = self.beats.get(beat["gateway"])
        self.beats[beat["gateway"]] = beat["sequence"]
        # The first seen, a jump, or a restarted gateway: heartbeats were lost.
        lost_beats = previous is None or beat["sequence"] != previous + 1
        listed = beat.get("sensors", {})
        for sensor, s in listed.items():
            if "late_timestamp_ns" in s:
                late = (s["late_sequence"], s["late_timestamp_ns"])
                hole = self.hole_of(sensor, late[1])
                if hole is not None:
                    self.fill_hole(sensor, hole, through=late)
            last = (s["last_sequence"], s["last_timestamp_ns"])
            mark = self.marks.get(sensor)
            if mark is not None and last[1] > mark[1]:
                self.recover(sensor, mark[1] + 1, through=last)
            elif mark is None and last[1] >= self.new_from_ns:
                self.recover(sensor, self.new_from_ns, through=last)
        if lost_beats:
            # A sensor that fell silent while the heartbeats naming its last batches were lost
            # is named in none: read on from where every sensor not named here was left.
            for sensor, mark in list(self.marks.items()):
                if sensor not in listed:
                    self.recover(sensor, mark[1] + 1)

    def poll(self):
        """The batches ready now, in order (an empty list if none)."""
        while True:
            sample = self.beats_sub.try_recv()
            if sample is None:
                break
            self.on_heartbeat(sample.payload.to_bytes())
        while True:
            sample = self.live.try_recv()
            if sample is None:
                break
            try:
                self.on_live(sample.payload.to_bytes())
            except DecodeError as e:
                print(f"{sample.key_expr}: refused: {e}", file=sys.stderr)
        ready, self.ready = self.ready, []
        return ready


def resume_state(path):
    """What a follower resumes from, read from an output file of `follow --out`: per sensor the
    position (sequence, timestamp_ns) of the last batch, duplicates and late batches aside, and
    the holes still open behind it (§5.2 steps 5 and 6), found by handing the file's batches
    over again in their order. A line cut short by a kill is removed: its batch was not handed
    over, and comes again from the history."""
    replay = Follower.__new__(Follower)
    replay.marks, replay.holes, replay.ready, replay.late = {}, {}, [], 0
    # A sensor's first batch in the file opens no hole below it: what came before it is not
    # known from the file.
    replay.new_from_ns = 2**63
    try:
        with open(path, "rb") as f:
            data = f.read()
    except FileNotFoundError:
        return {}, {}
    whole = data[: data.rfind(b"\n") + 1]
    if len(whole) != len(data):
        with open(path, "r+b") as f:
            f.truncate(len(whole))
    for line in whole.splitlines():
        b = json.loads(line)
        replay.hand_over(None, b)
        replay.ready.clear()
    last = {s: (m[0], m[1]) for s, m in replay.marks.items()}
    return last, replay.holes


def cmd_follow(args):
    session = open_session(args)
    last, holes = resume_state(args.out) if args.out else ({}, {})
    follower = Follower(session, args.building, last, holes=holes)
    out = open(args.out, "a", buffering=1) if args.out else sys.stdout
    print(json.dumps({"event": "ready", "resumed_sensors": len(last)}), file=sys.stderr, flush=True)
    handed = 0
    try:
        while args.count == 0 or handed < args.count:
            ready = follower.poll()
            if not ready:
                time.sleep(0.005)
                continue
            for payload, batch in ready:
                key = f"{ROOT}/{args.building}/corrected/{batch['sensor_id']}"
                line = json.loads(batch_json(key, batch))
                line["payload_hex"] = payload.hex()
                # One write per line: a kill leaves at most the last line cut short.
                out.write(json.dumps(line) + "\n")
                handed += 1
    except KeyboardInterrupt:
        pass
    finally:
        session.close()
    return 0


def cmd_simulate(args):
    session = open_session(args)
    key = raw_key(args.building, args.sensor)
    # Let the session connect and learn its peers' subscriptions before the first put.
    time.sleep(args.warmup_s)
    rate = args.rate_hz
    n = args.batch_samples
    t0_ns = time.time_ns() if args.start_ns is None else args.start_ns
    sent = 0
    try:
        while args.count == 0 or sent < args.count:
            seq = args.start_sequence + sent
            first = sent * n
            samples = []
            for i in range(n):
                t = (first + i) / rate
                a = (args.amplitude_mps2 * math.sin(2 * math.pi * args.frequency_hz * t), 0.0, 9.81)
                # The node sees outputs, not accelerations: V = gain·(a − offset), per axis.
                samples.append(tuple(args.gain * (ai - args.offset_mps2) for ai in a))
            ts = t0_ns + round(first * 1e9 / rate)
            payload = encode_raw(args.sensor, seq, ts, rate, samples, args.temperature_c)
            session.put(key, payload)
            if args.json:
                # The values as they travel: rounded to f32 exactly as the payload holds them.
                as_sent = [list(struct.unpack("<3f", struct.pack("<3f", *v))) for v in samples]
                print(
                    json.dumps(
                        {"key": key, "sequence": seq, "timestamp_ns": ts, "sample_rate_hz": rate,
                         "samples": as_sent}
                    ),
                    flush=True,
                )
            sent += 1
            time.sleep(args.interval_s if args.interval_s is not None else n / rate)
    except KeyboardInterrupt:
        pass
    finally:
        # Give the last put time to leave before the session goes.
        time.sleep(0.2)
        session.close()
    return 0


# --- Alerts (PROTOCOL.md §3.6) ----------------------------------------------------------------

ALERT_SIGNING_CONTEXT = b"triax alert v1\0"


def read_alert(payload, trusted_keys):
    """(alert dict, trust) for an alert payload; trust is verified, unknown_key, bad_signature
    or unsigned. Raises ValueError when the payload is not an alert at all."""
    from cryptography.exceptions import InvalidSignature
    from cryptography.hazmat.primitives.asymmetric.ed25519 import Ed25519PublicKey

    m = json.loads(payload)
    if not isinstance(m, dict):
        raise ValueError("not a JSON object")
    if "alert_json" not in m:
        if "kind" not in m or "level" not in m:
            raise ValueError("neither a signed alert nor an alert")
        return m, "unsigned"
    alert = json.loads(m["alert_json"])
    try:
        key = bytes.fromhex(m["public_key_hex"])
        if m.get("algorithm") != "ed25519" or len(key) != 32:
            return alert, "bad_signature"
        Ed25519PublicKey.from_public_bytes(key).verify(
            bytes.fromhex(m["signature_hex"]), ALERT_SIGNING_CONTEXT + m["alert_json"].encode())
    except (InvalidSignature, ValueError, KeyError):
        return alert, "bad_signature"
    return alert, ("verified" if key in trusted_keys else "unknown_key")


def cmd_alerts(args):
    trusted = set()
    for k in args.trusted_alert_key:
        trusted.add(bytes.fromhex(k.strip()))
    for path in args.trusted_alert_key_file:
        with open(path) as f:
            trusted.add(bytes.fromhex(f.read().strip()))
    session = open_session(args)
    sub = session.declare_subscriber(f"{ROOT}/{args.building}/alert/*")
    seen = 0
    try:
        for sample in sub:
            try:
                alert, trust = read_alert(sample.payload.to_bytes(), trusted)
            except ValueError as e:
                print(json.dumps({"key": str(sample.key_expr), "error": str(e)}), flush=True)
                continue
            if args.json:
                print(json.dumps({"key": str(sample.key_expr), "trust": trust, "alert": alert}), flush=True)
            elif trust == "verified":
                print(f"{alert['building']}/{alert['sensor_id']} {alert['kind']} {alert['level']}: "
                      f"{alert['value']} ± {alert['coverage_factor'] * alert['standard_uncertainty']} "
                      f"{alert['unit']} against {alert['threshold']}", flush=True)
            else:
                print(f"NOT A VERDICT ({trust}): something on {sample.key_expr} claims "
                      f"{alert.get('kind')} {alert.get('level')}", flush=True)
            seen += 1
            if args.count and seen >= args.count:
                break
    finally:
        session.close()
    return 0


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    common = argparse.ArgumentParser(add_help=False)
    common.add_argument("--building", default="hq")
    common.add_argument("--mode", choices=["peer", "client"], default="peer")
    common.add_argument("--connect", action="append", default=[], help="endpoint, repeatable")
    common.add_argument("--listen", action="append", default=[], help="endpoint, repeatable")
    common.add_argument("--no-multicast", action="store_true", help="turn off multicast scouting")
    common.add_argument("--count", type=int, default=0, help="stop after this many batches (0: never)")
    common.add_argument("--json", action="store_true", help="one JSON object per batch")
    sub = p.add_subparsers(dest="command", required=True)

    s = sub.add_parser("subscribe", parents=[common], help="decode and print corrected batches")
    s.add_argument("--sensor", help="one sensor (default: every sensor of the building)")
    s.add_argument("--timeout-s", type=float, default=0, help="give up after this long (0: never)")

    f = sub.add_parser("follow", parents=[common], help="corrected batches, losing nothing")
    f.add_argument("--out", help="append JSON lines here, and resume from what it holds")

    m = sub.add_parser("simulate", parents=[common], help="publish raw batches as a sensor node")
    m.add_argument("--sensor", default="py-01")
    m.add_argument("--rate-hz", type=float, default=100.0)
    m.add_argument("--batch-samples", type=int, default=50)
    m.add_argument("--amplitude-mps2", type=float, default=0.2)
    m.add_argument("--frequency-hz", type=float, default=2.0)
    m.add_argument("--gain", type=float, default=0.1, help="output unit per m/s^2")
    m.add_argument("--offset-mps2", type=float, default=0.0)
    m.add_argument("--temperature-c", type=float)
    m.add_argument("--start-sequence", type=int, default=0)
    m.add_argument("--start-ns", type=int, help="timestamp of the first sample (default: now)")
    m.add_argument("--interval-s", type=float, help="pause between batches (default: real time)")
    m.add_argument("--warmup-s", type=float, default=1.0)

    a = sub.add_parser("alerts", parents=[common], help="alerts, each verified or said not to be")
    a.add_argument("--trusted-alert-key", action="append", default=[],
                   help="an alerting service's public key, 64 hex characters (repeatable)")
    a.add_argument("--trusted-alert-key-file", action="append", default=[],
                   help="a file holding one, e.g. triax-alert.key.pub (repeatable)")

    args = p.parse_args(argv)
    commands = {"subscribe": cmd_subscribe, "follow": cmd_follow, "simulate": cmd_simulate,
                "alerts": cmd_alerts}
    return commands[args.command](args)


if __name__ == "__main__":
    sys.exit(main())
