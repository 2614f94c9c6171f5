//! The history on a real directory: what is flushed comes back bit for bit, by time, sequence
//! and arrival; a torn end is cut after a crash; retention keeps the size cap; a damaged block is
//! reported and never served.

use std::path::Path;

use triax_history::{Block, History, HistoryConfig, Kept, Opened, Query, Verdict};
use triax_protocol::{InlineId, SensorId};

fn inline(s: &str) -> InlineId {
    InlineId::new(&id(s))
}

fn id(s: &str) -> SensorId {
    SensorId::new(s).unwrap()
}

/// Batch `seq` of a 100 Hz sensor sending 10 samples per batch; sample values encode (seed, seq,
/// index) so that any mix-up shows.
fn samples(seed: u32, seq: u64) -> Vec<u8> {
    (0..30)
        .flat_map(|i| (seed as f32 * 1000.0 + seq as f32 + i as f32 / 64.0).to_le_bytes())
        .collect()
}

fn ts(seq: u64) -> i64 {
    1_800_000_000_000_000_000 + seq as i64 * 100_000_000
}

fn kept(seq: u64, samples: &[u8]) -> Kept<&[u8]> {
    Kept {
        arrival: 0,
        sequence: seq,
        timestamp_ns: ts(seq),
        sample_rate_hz: 100.0,
        temperature_c: None,
        calibration_version: 1 + seq / 100,
        verdict: Verdict::InOrder,
        samples,
    }
}

fn open(dir: &Path, max_bytes: u64, segment_bytes: u64) -> Opened {
    let mut c = HistoryConfig::new(dir);
    c.max_bytes = max_bytes;
    c.segment_bytes = segment_bytes;
    History::open(c).unwrap()
}

/// What a scan yields: the checkpoint of its first block, and each wanted batch's sequence
/// number and samples.
type Read = (Option<Vec<u8>>, Vec<(u64, Vec<u8>)>);

fn read(h: &History, q: &Query) -> Read {
    let mut scan = h.scan(q).unwrap();
    let mut first_checkpoint = None;
    let mut out = Vec::new();
    let mut first = true;
    while let Some(b) = scan.next_block() {
        let b = b.unwrap();
        let block = Block::decode(&b.bytes).unwrap();
        assert_eq!(block.sensor, q.sensor);
        if first {
            first_checkpoint = block.checkpoint.map(<[u8]>::to_vec);
            first = false;
        }
        for k in block.kept.iter().filter(|k| q.matches(*k)) {
            out.push((k.sequence, k.samples.to_vec()));
        }
    }
    (first_checkpoint, out)
}

#[test]
fn flushed_batches_come_back_by_time_sequence_and_arrival_across_segments_and_reopen() {
    let dir = tempfile::tempdir().unwrap();
    {
        // Small segments: the stream spans many.
        let Opened { mut writer, .. } = open(dir.path(), u64::MAX, 32 << 10);
        for seq in 0..1000u64 {
            for (seed, s) in [(1, "a"), (2, "b"), (3, "c")] {
                // A checkpoint every 100 batches, as the gateway's every 10 s of data.
                let ck = (seq % 100 == 0).then(|| format!("ck {s} {seq}").into_bytes());
                let smp = samples(seed, seq);
                writer.append(&inline(s), kept(seq, &smp), ck.as_deref());
            }
            if seq % 10 == 9 {
                writer.flush().unwrap();
            }
        }
        writer.flush().unwrap();
        assert!(writer.history().stats().segments > 10);
    }
    let Opened { history: h, .. } = open(dir.path(), u64::MAX, 32 << 10);
    assert_eq!(h.sensors(), [id("a"), id("b"), id("c")]);
    let mut q = Query::all(id("b"));
    let (_, all) = read(&h, &q);
    assert_eq!(all.len(), 1000);
    for (i, (seq, smp)) in all.iter().enumerate() {
        assert_eq!(*seq, i as u64);
        assert_eq!(smp, &samples(2, i as u64), "batch {i} bit for bit");
    }
    // A time range starting mid-way: the scan starts at the checkpoint before it.
    q.from_ns = Some(ts(455));
    q.to_ns = Some(ts(470));
    let (ck, got) = read(&h, &q);
    assert_eq!(ck.as_deref(), Some(&b"ck b 400"[..]));
    assert_eq!(
        got.iter().map(|g| g.0).collect::<Vec<_>>(),
        (455..470).collect::<Vec<_>>()
    );
    // A sequence range.
    let mut q = Query::all(id("c"));
    q.from_seq = Some(998);
    let (ck, got) = read(&h, &q);
    assert_eq!(ck.as_deref(), Some(&b"ck c 900"[..]));
    assert_eq!(got.len(), 2);
    // Arrival numbers order all three sensors: `a` came first in each round.
    let scan_arrivals = |s: &str| -> Vec<u64> {
        let mut scan = h.scan(&Query::all(id(s))).unwrap();
        let mut v = Vec::new();
        while let Some(b) = scan.next_block() {
            v.extend(
                Block::decode(&b.unwrap().bytes)
                    .unwrap()
                    .kept
                    .iter()
                    .map(|k| k.arrival),
            );
        }
        v
    };
    let (a, b) = (scan_arrivals("a"), scan_arrivals("b"));
    assert_eq!(a.len(), 1000);
    assert!(a.iter().zip(&b).all(|(x, y)| y == &(x + 1)));
    // After a cursor.
    let mut q = Query::all(id("a"));
    q.after_arrival = Some(a[997]);
    assert_eq!(read(&h, &q).1.len(), 2);
    // Writing again continues the arrival order.
    drop(h);
    let Opened { mut writer, .. } = open(dir.path(), u64::MAX, 32 << 10);
    let smp = samples(1, 1000);
    let arrival = writer.append(&inline("a"), kept(1000, &smp), None);
    assert_eq!(arrival, a[999] + 3, "after c's last batch");
}

#[test]
fn a_torn_end_is_cut_and_everything_flushed_before_it_kept() {
    let dir = tempfile::tempdir().unwrap();
    {
        let Opened { mut writer, .. } = open(dir.path(), u64::MAX, 64 << 20);
        for seq in 0..50u64 {
            let smp = samples(1, seq);
            writer.append(
                &inline("a"),
                kept(seq, &smp),
                (seq == 0).then_some(&b"x"[..]),
            );
            writer.flush().unwrap();
        }
    }
    // A crash mid-write: half a frame at the end of the log, and an index entry torn in two.
    let log = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "log"))
        .max()
        .unwrap();
    let idx = log.with_extension("idx");
    let mut bytes = std::fs::read(&log).unwrap();
    let good_len = bytes.len();
    bytes.extend_from_slice(&[200, 0, 0, 0, 1, 2, 3, 4, 5, 6, 7]);
    std::fs::write(&log, &bytes).unwrap();
    let mut ib = std::fs::read(&idx).unwrap();
    // Three whole entries lost and a fourth torn.
    ib.truncate(ib.len() - 72 * 3 - 10);
    std::fs::write(&idx, &ib).unwrap();

    let opened = open(dir.path(), u64::MAX, 64 << 20);
    assert_eq!(opened.cut_bytes, 11);
    assert_eq!(
        opened.rescanned_blocks, 4,
        "the lost index entries are rebuilt"
    );
    assert_eq!(std::fs::metadata(&log).unwrap().len() as usize, good_len);
    let (ck, got) = read(&opened.history, &Query::all(id("a")));
    assert_eq!(ck.as_deref(), Some(&b"x"[..]));
    assert_eq!(got.len(), 50);
}

#[test]
fn a_damaged_block_is_reported_and_the_rest_served() {
    let dir = tempfile::tempdir().unwrap();
    let Opened {
        mut writer,
        history,
        ..
    } = open(dir.path(), u64::MAX, 64 << 20);
    for seq in 0..3u64 {
        let smp = samples(1, seq);
        writer.append(&inline("a"), kept(seq, &smp), None);
        writer.flush().unwrap();
    }
    // Flip one sample bit of the middle block, on disk.
    let log = std::fs::read_dir(dir.path())
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "log"))
        .max()
        .unwrap();
    let mut bytes = std::fs::read(&log).unwrap();
    let block_len = bytes.len() / 3;
    bytes[block_len + block_len / 2] ^= 0x10;
    std::fs::write(&log, &bytes).unwrap();
    let mut scan = history.scan(&Query::all(id("a"))).unwrap();
    let results: Vec<_> = std::iter::from_fn(|| scan.next_block()).collect();
    assert_eq!(results.len(), 3);
    assert!(results[0].is_ok() && results[2].is_ok());
    let err = results[1].as_ref().unwrap_err().to_string();
    assert!(err.contains("damaged block"), "{err}");
}

#[test]
fn retention_keeps_the_size_cap_oldest_first() {
    let dir = tempfile::tempdir().unwrap();
    let cap = 200 << 10;
    let Opened {
        mut writer,
        history,
        ..
    } = open(dir.path(), cap, 16 << 10);
    for seq in 0..5000u64 {
        let smp = samples(1, seq);
        writer.append(
            &inline("a"),
            kept(seq, &smp),
            (seq % 50 == 0).then_some(&b"ck"[..]),
        );
        if seq % 20 == 19 {
            writer.flush().unwrap();
        }
        let on_disk: u64 = std::fs::read_dir(dir.path())
            .unwrap()
            .map(|e| e.unwrap().metadata().unwrap().len())
            .sum();
        // The cap, plus the segment being written and one pending flush.
        assert!(
            on_disk <= cap + (16 << 10) + 20 * 200,
            "{on_disk} bytes on disk"
        );
    }
    writer.flush().unwrap();
    let stats = history.stats();
    assert!(stats.bytes <= cap, "{stats:?}");
    let deleted = history
        .counters
        .deleted_segments
        .load(std::sync::atomic::Ordering::Relaxed);
    assert!(deleted > 10, "{deleted} segments deleted");
    // What is left is the newest stretch, contiguous up to the last batch.
    let (_, got) = read(&history, &Query::all(id("a")));
    let seqs: Vec<u64> = got.iter().map(|g| g.0).collect();
    assert_eq!(*seqs.last().unwrap(), 4999);
    assert!(seqs.windows(2).all(|w| w[1] == w[0] + 1));
    assert!(seqs[0] > 3000, "oldest kept {}", seqs[0]);
}

#[test]
fn one_writer_per_directory() {
    let dir = tempfile::tempdir().unwrap();
    let _first = open(dir.path(), u64::MAX, 64 << 20);
    let second = History::open(HistoryConfig::new(dir.path())).unwrap_err();
    assert!(second.to_string().contains("in use"), "{second}");
}

/// A stream as heavy as a saturated gateway's (100-sample batches, megabyte blocks): closed
/// blocks are written ahead of the flush, long runs go past the page cache, and every batch
/// comes back bit for bit; readers see a block only once a flush made it durable.
#[test]
fn a_heavy_stream_written_ahead_and_past_the_page_cache_comes_back_bit_for_bit() {
    let dir = tempfile::tempdir().unwrap();
    let batch = |seed: u32, seq: u64| -> Vec<u8> {
        (0..300)
            .flat_map(|i| (seed as f32 * 1e6 + seq as f32 + i as f32 / 512.0).to_le_bytes())
            .collect()
    };
    let sensors = ["a", "b", "c", "d"];
    {
        let Opened {
            mut writer,
            history: h,
            ..
        } = open(dir.path(), u64::MAX, 8 << 20);
        let mut flushed = 0;
        for seq in 0..6000u64 {
            for (k, s) in sensors.iter().enumerate() {
                let smp = batch(k as u32, seq);
                let ck = (seq % 2000 == 0).then(|| format!("ck {s} {seq}").into_bytes());
                writer.append(&inline(s), kept(seq, &smp), ck.as_deref());
            }
            if seq % 1500 == 1499 {
                // Megabytes were written ahead since the last flush, none of it served yet.
                assert_eq!(read(&h, &Query::all(id("c"))).1.len(), flushed);
                writer.flush().unwrap();
                flushed = seq as usize + 1;
                assert_eq!(read(&h, &Query::all(id("c"))).1.len(), flushed);
            }
        }
        writer.flush().unwrap();
        let direct = h
            .counters
            .direct_bytes
            .load(std::sync::atomic::Ordering::Relaxed);
        if triax_history::append::direct_supported(dir.path()) {
            // 29 MB in flushes of 7 MB: nearly all of it direct.
            assert!(direct > 25 << 20, "{direct} bytes written directly");
        }
        assert!(h.stats().segments >= 3);
    }
    let Opened { history: h, .. } = open(dir.path(), u64::MAX, 8 << 20);
    for (k, s) in sensors.iter().enumerate() {
        let (_, all) = read(&h, &Query::all(id(s)));
        assert_eq!(all.len(), 6000, "sensor {s}");
        for (i, (seq, smp)) in all.iter().enumerate() {
            assert_eq!(*seq, i as u64);
            assert!(
                *smp == batch(k as u32, i as u64),
                "{s} batch {i} bit for bit"
            );
        }
    }
    let mut q = Query::all(id("b"));
    q.from_seq = Some(4100);
    q.to_seq = Some(4110);
    let (ck, got) = read(&h, &q);
    assert_eq!(ck.as_deref(), Some(&b"ck b 4000"[..]));
    assert_eq!(got.len(), 11);
}

/// A crash after blocks were written ahead of a flush, with the page before the first direct
/// page lost (as power loss can leave it: the direct pages reached the disk, the page cache's
/// did not): opening keeps every flushed block, cuts at the hole, and serves nothing after it.
#[test]
fn a_crash_between_write_ahead_and_flush_keeps_what_was_flushed_and_cuts_at_the_hole() {
    let dir = tempfile::tempdir().unwrap();
    let batch = |seq: u64| -> Vec<u8> {
        (0..300)
            .flat_map(|i| (seq as f32 + i as f32 / 512.0).to_le_bytes())
            .collect()
    };
    let flushed_end;
    {
        let Opened { mut writer, .. } = open(dir.path(), u64::MAX, 64 << 20);
        for seq in 0..100u64 {
            let smp = batch(seq);
            writer.append(
                &inline("a"),
                kept(seq, &smp),
                (seq == 0).then_some(&b"x"[..]),
            );
        }
        writer.flush().unwrap();
        let log = newest_log(dir.path());
        flushed_end = std::fs::metadata(&log).unwrap().len();
        // Megabytes more, closed into blocks and written ahead, never flushed.
        for seq in 100..6000u64 {
            let smp = batch(seq);
            let ck = (seq % 500 == 0).then_some(&b"y"[..]);
            writer.append(&inline("a"), kept(seq, &smp), ck);
        }
        assert!(std::fs::metadata(&log).unwrap().len() > flushed_end + (1 << 20));
        // Dropped without a flush: a kill.
    }
    let log = newest_log(dir.path());
    let mut bytes = std::fs::read(&log).unwrap();
    let len = bytes.len() as u64;
    let start = flushed_end as usize;
    let hole_end = (start + 100).min(bytes.len());
    bytes[start..hole_end].fill(0);
    std::fs::write(&log, &bytes).unwrap();

    let opened = open(dir.path(), u64::MAX, 64 << 20);
    assert_eq!(opened.cut_bytes, len - flushed_end);
    assert_eq!(std::fs::metadata(&log).unwrap().len(), flushed_end);
    let (ck, got) = read(&opened.history, &Query::all(id("a")));
    assert_eq!(ck.as_deref(), Some(&b"x"[..]));
    assert_eq!(got.len(), 100);
    for (i, (seq, smp)) in got.iter().enumerate() {
        assert_eq!(*seq, i as u64);
        assert!(*smp == batch(i as u64));
    }
}

/// The newest segment's log in `dir`.
fn newest_log(dir: &Path) -> std::path::PathBuf {
    std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.extension().is_some_and(|e| e == "log"))
        .max()
        .unwrap()
}

/// The writer keeps a sensor from flush to flush rather than meeting it anew after each, and
/// forgets it at a roll: every closed segment's list of sensors is exactly the sensors its index
/// holds blocks of, for sensors that stream through several flushes and segments, stop, or
/// start late.
#[test]
fn each_closed_segment_names_exactly_the_sensors_it_holds() {
    use std::collections::BTreeSet;
    use triax_history::segment;
    let dir = tempfile::tempdir().unwrap();
    let Opened {
        mut writer,
        history,
        ..
    } = open(dir.path(), u64::MAX, 2500);
    for round in 0..16u64 {
        let streaming: &[&str] = match round {
            0..=2 => &["a", "b"],
            3..=9 => &["a"],
            _ => &["a", "c"],
        };
        for (i, s) in streaming.iter().enumerate() {
            for k in 0..5 {
                let seq = round * 5 + k;
                let smp = samples(i as u32, seq);
                writer.append(&inline(s), kept(seq, &smp), None);
            }
        }
        writer.flush().unwrap();
    }
    drop(writer);
    drop(history);
    let mut ids: Vec<u64> = std::fs::read_dir(dir.path())
        .unwrap()
        .filter_map(|e| {
            let p = e.unwrap().path();
            let stem = p.file_stem()?.to_str()?.to_owned();
            (p.extension()? == "log").then(|| stem.parse().unwrap())
        })
        .collect();
    ids.sort_unstable();
    // The newest is still open; every other one closed, with its meta.
    let closed = &ids[..ids.len() - 1];
    assert!(closed.len() >= 4, "{ids:?}");
    let mut named_over_all = BTreeSet::new();
    for &seg in closed {
        let meta = segment::read_meta(dir.path(), seg).unwrap();
        let named: BTreeSet<u64> = meta
            .sensors
            .iter()
            .map(|s| segment::sensor_hash(s.as_str()))
            .collect();
        let held: BTreeSet<u64> = segment::read_index(dir.path(), seg)
            .unwrap()
            .iter()
            .map(|e| e.sensor_hash)
            .collect();
        assert_eq!(named, held, "segment {seg}: {:?}", meta.sensors);
        named_over_all.extend(meta.sensors);
    }
    assert_eq!(named_over_all, [id("a"), id("b"), id("c")].into());
}

/// What the history holds of a sensor is found across every gateway run, also past segments
/// that hold none of it: a sensor cut off while the gateway restarted twice (each start a
/// segment of its own, filled by the other sensor) still has its earlier numbers found, and
/// only the numbers it really lacks show as holes. The same history reopened after each run,
/// as a gateway does.
#[test]
fn a_sensors_runs_are_found_past_segments_without_it() {
    use triax_history::SeqRun;
    let dir = tempfile::tempdir().unwrap();
    // Runs of the gateway: which sensor streams which numbers.
    let runs: [&[(&str, std::ops::Range<u64>)]; 4] = [
        &[("cut", 0..40), ("steady", 0..40)],
        &[("steady", 40..80)],
        &[("steady", 80..120)],
        &[("cut", 50..60), ("steady", 120..130)],
    ];
    let mut first_arrival_of_last = 0;
    for (i, run) in runs.iter().enumerate() {
        let Opened {
            mut writer,
            history,
            ..
        } = open(dir.path(), u64::MAX, 32 << 20);
        if i == runs.len() - 1 {
            // The last run: what did the runs before it keep of `cut`, below its first batch?
            first_arrival_of_last = writer.next_arrival();
            let got = history
                .kept_runs(&id("cut"), first_arrival_of_last, 0, ts(120))
                .unwrap();
            assert_eq!(
                got,
                vec![SeqRun {
                    first_seq: 0,
                    first_ns: ts(0),
                    last_seq: 39,
                    last_ns: ts(39),
                }],
                "the first run's numbers, found past the two segments without the sensor"
            );
            // A span starting above everything kept: nothing, and the search stops.
            assert!(history
                .kept_runs(&id("cut"), first_arrival_of_last, 45, ts(120))
                .unwrap()
                .is_empty());
            assert!(history
                .kept_runs(&id("never"), first_arrival_of_last, 0, ts(120))
                .unwrap()
                .is_empty());
        }
        for (s, seqs) in run.iter() {
            for seq in seqs.clone() {
                let smp = samples(0, seq);
                writer.append(&inline(s), kept(seq, &smp), None);
            }
        }
        writer.flush().unwrap();
    }
    assert!(first_arrival_of_last > 0);
}
