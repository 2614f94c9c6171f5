//! How the gateway keeps its resident memory near what it uses.
//!
//! Two habits of glibc's allocator cost a gateway with ten thousand sensors tens of MiB:
//!
//! - Start-up is a burst: every stored record is read and decoded (on every core, so in several
//!   allocator arenas) and only the compact corrector is kept. The freed pages of that burst
//!   stay resident in each thread's arena. Sensors coming online do the same on a smaller
//!   scale: their lasting state is allocated among the short-lived buffers of their first
//!   batches. [`release_free_heap`] hands the freed pages back; it is called after such growth
//!   has settled, never on the sample path, because it walks every arena under its lock.
//! - By default the threshold above which an allocation gets its own mapping rises to the size
//!   of the largest such block freed, up to 32 MiB. After the start-up burst frees its
//!   megabyte-sized buffers, later large blocks then come from the arenas, where they fragment
//!   the heap and, once freed, stay resident. [`configure_allocator`] pins the threshold at
//!   glibc's initial 128 KiB. Nothing on the sample path allocates that much: a corrected
//!   batch of 100 samples is 2.5 KiB.
//!
//! Both are process-wide, so the binaries call [`configure_allocator`] first thing; the library
//! calls [`release_free_heap`] itself, after start-up and from [`release_after_growth`].

use std::sync::atomic::Ordering::Relaxed;
use std::sync::Arc;
use std::time::Duration;

use super::{Context, Task};
use crate::shutdown::Shutdown;
use crate::state::GatewayCounters;

/// The fixed threshold: glibc's default starting value.
#[cfg(all(target_os = "linux", target_env = "gnu"))]
const MMAP_THRESHOLD_BYTES: libc::c_int = 128 * 1024;

/// Pins the allocator's mmap threshold (see the module notes). Call it once, before the
/// runtime starts its threads; a no-op where the allocator is not glibc's.
pub fn configure_allocator() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: `mallopt` only sets an allocator parameter; M_MMAP_THRESHOLD with a value within
    // glibc's bounds (at most 32 MiB on 64-bit) is always accepted.
    unsafe {
        libc::mallopt(libc::M_MMAP_THRESHOLD, MMAP_THRESHOLD_BYTES);
    }
}

/// Returns free heap pages to the system; a no-op where the allocator has no such call.
pub fn release_free_heap() {
    #[cfg(all(target_os = "linux", target_env = "gnu"))]
    // SAFETY: `malloc_trim` only releases pages of free chunks; it is thread-safe (each arena
    // is trimmed under its own lock) and touches no memory the program owns.
    unsafe {
        libc::malloc_trim(0);
    }
}

/// The process's resident set, from `/proc/self/statm`; none where there is no procfs.
pub fn resident_bytes() -> Option<u64> {
    let statm = std::fs::read_to_string("/proc/self/statm").ok()?;
    let pages: u64 = statm.split_whitespace().nth(1)?.parse().ok()?;
    Some(pages * page_size_bytes())
}

fn page_size_bytes() -> u64 {
    #[cfg(unix)]
    {
        // SAFETY: sysconf reads a constant of the system; it has no preconditions.
        let size = unsafe { libc::sysconf(libc::_SC_PAGESIZE) };
        if let Ok(size) = u64::try_from(size) {
            if size > 0 {
                return size;
            }
        }
    }
    4096
}

/// How long the heap must stay unchanged after growth before [`release_after_growth`] trims it.
pub const GROWTH_SETTLE_PERIOD: Duration = Duration::from_secs(1);

/// What makes the heap grow for good: sensors coming online and calibrations installed.
fn growth(counters: &GatewayCounters) -> (u64, u64) {
    (
        counters.sensors_online.load(Relaxed),
        counters.pushes_accepted.load(Relaxed),
    )
}

/// Calls [`release_free_heap`] once the heap has grown and then settled: when sensors came
/// online or calibrations were installed since the last release, and nothing changed during
/// the last `period`. A burst of sensors joining allocates their lasting state among the
/// short-lived buffers of their first batches; once the burst is over, the holes those buffers
/// leave are handed back. In the steady state nothing grows and this never trims.
pub async fn release_after_growth(
    counters: Arc<GatewayCounters>,
    period: Duration,
    shutdown: Shutdown,
) {
    release_when_settled(
        || growth(&counters),
        period,
        shutdown,
        || async {
            tokio::task::spawn_blocking(release_free_heap).await.ok();
            tracing::debug!(
                resident_bytes = resident_bytes(),
                "released free heap after growth"
            );
        },
    )
    .await;
}

/// The rule of [`release_after_growth`], over any measure of growth and any release.
async fn release_when_settled<G, R, F>(
    growth: impl Fn() -> G,
    period: Duration,
    mut shutdown: Shutdown,
    release: R,
) where
    G: PartialEq + Copy,
    R: Fn() -> F,
    F: std::future::Future<Output = ()>,
{
    let mut released = growth();
    let mut previous = released;
    let mut tick = tokio::time::interval(period);
    tick.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Delay);
    loop {
        tokio::select! {
            _ = tick.tick() => {}
            _ = shutdown.recv() => break,
        }
        let now = growth();
        if now == previous && now != released {
            release().await;
            released = now;
        }
        previous = now;
    }
}

/// Starts [`release_after_growth`].
pub fn start(ctx: &Context) -> Task {
    tokio::spawn(release_after_growth(
        ctx.counters.clone(),
        GROWTH_SETTLE_PERIOD,
        ctx.shutdown.clone(),
    ))
}

/// [`release_free_heap`] off the runtime's threads, once the store's records have been read.
pub async fn release_loading_heap() -> Result<(), crate::error::GatewayError> {
    tokio::task::spawn_blocking(release_free_heap)
        .await
        .map_err(|e| crate::error::GatewayError::Task(e.to_string()))
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::sync::atomic::AtomicU64;

    /// Ticks of `period`, paused time: growth at chosen ticks, releases counted.
    #[tokio::test(start_paused = true)]
    async fn releases_once_after_growth_settles_and_never_in_the_steady_state() {
        let period = Duration::from_secs(1);
        let grown = Arc::new(AtomicU64::new(0));
        let releases = Arc::new(AtomicU64::new(0));
        let (trigger, shutdown) = crate::shutdown::channel();
        let (g, r) = (grown.clone(), releases.clone());
        let task = tokio::spawn(release_when_settled(
            move || g.load(Relaxed),
            period,
            shutdown,
            move || {
                r.fetch_add(1, Relaxed);
                std::future::ready(())
            },
        ));
        let at_tick = |k: u64| Duration::from_millis(1000 * k + 500);
        let start = tokio::time::Instant::now();
        let sleep_to = |k: u64| tokio::time::sleep_until(start + at_tick(k));

        sleep_to(3).await;
        assert_eq!(releases.load(Relaxed), 0, "no growth, no release");
        // Growth on three consecutive ticks: no release while it goes on.
        for k in 3..6 {
            grown.fetch_add(100, Relaxed);
            sleep_to(k + 1).await;
        }
        assert_eq!(releases.load(Relaxed), 0, "still growing at the last tick");
        sleep_to(7).await;
        assert_eq!(
            releases.load(Relaxed),
            1,
            "one release once a tick saw no change"
        );
        sleep_to(12).await;
        assert_eq!(
            releases.load(Relaxed),
            1,
            "steady state: no further release"
        );
        grown.fetch_add(1, Relaxed);
        sleep_to(15).await;
        assert_eq!(releases.load(Relaxed), 2, "new growth, one more release");
        trigger.fire();
        task.await.unwrap();
    }
}
