//! What a bench reads of a process from /proc: CPU time, context switches and resident set,
//! for the whole process and per thread (the end-to-end benches of `triax-bench`, and the
//! alerting, modes and console services' benches).

use std::path::Path;

use anyhow::{Context, Result};

/// Context switches, voluntary and not, summed over every thread of a process, from
/// `/proc/<pid>/task/*/status`. Threads that ended meanwhile are not counted.
pub fn context_switches(pid: u32) -> Result<u64> {
    let mut total = 0;
    for task in std::fs::read_dir(format!("/proc/{pid}/task"))? {
        let Ok(text) = std::fs::read_to_string(task?.path().join("status")) else {
            continue;
        };
        for line in text.lines() {
            if let Some(rest) = line
                .strip_prefix("voluntary_ctxt_switches:")
                .or_else(|| line.strip_prefix("nonvoluntary_ctxt_switches:"))
            {
                total += rest.trim().parse::<u64>()?;
            }
        }
    }
    Ok(total)
}

/// CPU time a process has used so far, user and system, all threads, from `/proc/<pid>/stat`
/// (in USER_HZ ticks, 100 per second on Linux).
pub fn cpu_seconds(pid: u32) -> Result<f64> {
    stat_cpu_seconds(Path::new(&format!("/proc/{pid}/stat")))
}

/// CPU seconds of the threads of a process with this name (`/proc/<pid>/task/*/comm`), summed
/// from their own `stat`; threads that ended meanwhile are not counted.
pub fn named_threads_cpu_seconds(pid: u32, name: &str) -> Result<f64> {
    let mut total = 0.0;
    for task in std::fs::read_dir(format!("/proc/{pid}/task"))? {
        let dir = task?.path();
        let Ok(comm) = std::fs::read_to_string(dir.join("comm")) else {
            continue;
        };
        if comm.trim() == name {
            total += stat_cpu_seconds(&dir.join("stat")).unwrap_or(0.0);
        }
    }
    Ok(total)
}

/// User and system CPU seconds of a `/proc/<pid>/stat` or `/proc/<pid>/task/<tid>/stat`.
fn stat_cpu_seconds(path: &Path) -> Result<f64> {
    let text = std::fs::read_to_string(path)?;
    // The command name is in parentheses and may hold spaces: count fields after it, from
    // field 3 (state); utime and stime are fields 14 and 15.
    let rest = text
        .rfind(')')
        .map(|i| &text[i + 1..])
        .context("/proc stat without a command name")?;
    let fields: Vec<&str> = rest.split_whitespace().collect();
    let ticks = |i: usize| -> Result<f64> {
        Ok(fields
            .get(i)
            .context("/proc stat too short")?
            .parse::<u64>()? as f64)
    };
    Ok((ticks(14 - 3)? + ticks(15 - 3)?) / 100.0)
}

/// One thread's counters so far: CPU time (user and system, ns, from `schedstat`) and the
/// times it slept and was woken (voluntary switches) or was preempted (involuntary).
#[derive(Debug, Default, Clone, Copy)]
pub struct ThreadCounters {
    cpu_ns: u64,
    voluntary: u64,
    involuntary: u64,
}

/// Every live thread of a process: its id, its name with the trailing index dropped (`rx-1`
/// and `rx-0` are both `rx`: a pool counts as one), and its counters.
pub fn thread_counters(pid: u32) -> Result<Vec<(u32, String, ThreadCounters)>> {
    let mut threads = Vec::new();
    for task in std::fs::read_dir(format!("/proc/{pid}/task"))? {
        let dir = task?.path();
        let Some(tid) = dir
            .file_name()
            .and_then(|n| n.to_str())
            .and_then(|n| n.parse().ok())
        else {
            continue;
        };
        // A thread that ends between the listing and the reads is left out.
        let (Ok(comm), Ok(sched), Ok(status)) = (
            std::fs::read_to_string(dir.join("comm")),
            std::fs::read_to_string(dir.join("schedstat")),
            std::fs::read_to_string(dir.join("status")),
        ) else {
            continue;
        };
        let name = comm
            .trim()
            .trim_end_matches(|c: char| c.is_ascii_digit())
            .trim_end_matches('-')
            .to_owned();
        let mut c = ThreadCounters {
            cpu_ns: sched
                .split_whitespace()
                .next()
                .and_then(|v| v.parse().ok())
                .unwrap_or(0),
            ..ThreadCounters::default()
        };
        for line in status.lines() {
            if let Some(v) = line.strip_prefix("voluntary_ctxt_switches:") {
                c.voluntary = v.trim().parse()?;
            } else if let Some(v) = line.strip_prefix("nonvoluntary_ctxt_switches:") {
                c.involuntary = v.trim().parse()?;
            }
        }
        threads.push((tid, name, c));
    }
    Ok(threads)
}

/// What each group of threads (by name) spent between two [`thread_counters`] readings, per
/// batch: µs of CPU, voluntary and involuntary switches, and how many threads the group has.
/// A thread that started meanwhile counts from zero; one that ended is missing.
pub fn per_thread_group(
    before: &[(u32, String, ThreadCounters)],
    after: &[(u32, String, ThreadCounters)],
    batches: f64,
) -> Vec<ThreadGroup> {
    let mut groups: std::collections::BTreeMap<&str, ThreadGroup> = Default::default();
    for (tid, name, c1) in after {
        let c0 = before
            .iter()
            .find(|(t, _, _)| t == tid)
            .map(|(_, _, c)| *c)
            .unwrap_or_default();
        let g = groups.entry(name).or_insert_with(|| ThreadGroup {
            name: name.clone(),
            ..ThreadGroup::default()
        });
        g.threads += 1;
        g.us_per_batch += c1.cpu_ns.saturating_sub(c0.cpu_ns) as f64 / 1e3 / batches;
        g.voluntary_per_batch += c1.voluntary.saturating_sub(c0.voluntary) as f64 / batches;
        g.involuntary_per_batch += c1.involuntary.saturating_sub(c0.involuntary) as f64 / batches;
    }
    groups.into_values().collect()
}

/// One group of threads in [`per_thread_group`].
#[derive(Debug, Default, Clone)]
pub struct ThreadGroup {
    pub name: String,
    pub threads: usize,
    pub us_per_batch: f64,
    pub voluntary_per_batch: f64,
    pub involuntary_per_batch: f64,
}

pub fn proc_status_kib(pid: u32, field: &str) -> Option<u64> {
    let text = std::fs::read_to_string(format!("/proc/{pid}/status")).ok()?;
    text.lines()
        .find(|l| l.starts_with(field))?
        .split_whitespace()
        .nth(1)?
        .parse()
        .ok()
}
