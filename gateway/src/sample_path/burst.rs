//! Items waiting for the end of their receive burst: the raw batches of the intake, in a queue
//! per shard, and the corrected batches of the outbox, in one.
//!
//! Zenoh's receive thread hands the gateway every message of one socket read in turn, and
//! Tokio runs a task spawned from a worker when the running one yields, which Zenoh's receive
//! task does when its socket has nothing more. So the first item of a burst queues a task, and
//! the task takes the whole burst once the read is done ([`Burst::push`], [`runtime`]).
//!
//! Invariants: items of a queue are taken in the order they were pushed, whole, and handed
//! over under one lock, so that two takes never interleave; at most [`BURST_MAX`] wait.

use std::sync::atomic::AtomicBool;
use std::sync::atomic::Ordering::Relaxed;
use std::sync::Mutex;

use crate::sync::lock;

/// Most items that wait for their burst's end; the push that makes this many asks for them to
/// be taken at once. A burst of 64 already shares its segments; a longer wait would only add
/// latency.
pub const BURST_MAX: usize = 64;

/// The runtime to queue a burst's task on: the caller's, when it is multi-threaded. A
/// single-threaded runtime would run the task only when its one task yields, and that may be a
/// caller blocked on what the burst answers. Looked up only when a task is to be queued: a
/// lookup counts the runtime's handle up and down, a line every receive thread shares.
pub fn runtime() -> Option<tokio::runtime::Handle> {
    tokio::runtime::Handle::try_current()
        .ok()
        .filter(|r| r.runtime_flavor() == tokio::runtime::RuntimeFlavor::MultiThread)
}

/// Items waiting for the end of their burst, one queue per shard.
pub struct Burst<T> {
    waiting: Mutex<Waiting<T>>,
    /// Whether a task that takes the burst is queued and has not yet started, or a take
    /// announced ([`Burst::announce`]).
    queued: AtomicBool,
    /// Held while a burst is handed over, so that two never interleave a queue's items; the
    /// queues are swapped into it whole and keep their room for the next burst.
    handling: Mutex<Vec<Vec<T>>>,
}

struct Waiting<T> {
    per_shard: Vec<Vec<T>>,
    len: usize,
}

/// What [`Burst::push`] asks of its caller.
#[derive(Debug, PartialEq, Eq)]
pub enum Pushed {
    /// A task queued earlier takes this item with the others.
    Waits,
    /// The first of a burst: queue a task that calls [`Burst::task_started`] and then takes
    /// the burst (or do both now, with no runtime to queue it on).
    First,
    /// [`BURST_MAX`] items wait: take them now.
    Full,
}

impl<T> Burst<T> {
    pub fn new(shards: usize) -> Burst<T> {
        let queues = || (0..shards).map(|_| Vec::with_capacity(BURST_MAX)).collect();
        Burst {
            waiting: Mutex::new(Waiting {
                per_shard: queues(),
                len: 0,
            }),
            queued: AtomicBool::new(false),
            handling: Mutex::new(queues()),
        }
    }

    pub fn push(&self, shard: usize, item: T) -> Pushed {
        let len = {
            let mut waiting = lock(&self.waiting);
            waiting.per_shard[shard].push(item);
            waiting.len += 1;
            waiting.len
        };
        if len >= BURST_MAX {
            Pushed::Full
        } else if self.queued.swap(true, Relaxed) {
            Pushed::Waits
        } else {
            Pushed::First
        }
    }

    /// The queued task started: an item pushed from now on queues another.
    pub fn task_started(&self) {
        self.queued.store(false, Relaxed);
    }

    /// A take is coming: pushes from now on wait for it rather than queue a task. True when no
    /// task was queued: the caller then calls [`task_started`](Self::task_started) before it
    /// takes; false: the task queued earlier will.
    pub fn announce(&self) -> bool {
        !self.queued.swap(true, Relaxed)
    }

    /// Takes every waiting item and hands each queue's, in arrival order, to `f`, which
    /// leaves the queue empty or has it cleared.
    pub fn take(&self, mut f: impl FnMut(usize, &mut Vec<T>)) {
        let mut handling = lock(&self.handling);
        {
            let mut waiting = lock(&self.waiting);
            if waiting.len == 0 {
                return;
            }
            waiting.len = 0;
            std::mem::swap(&mut *handling, &mut waiting.per_shard);
        }
        for (i, items) in handling.iter_mut().enumerate() {
            if !items.is_empty() {
                f(i, items);
                items.clear();
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use std::sync::Arc;

    use super::*;

    #[test]
    fn a_burst_is_taken_whole_in_order_per_shard() {
        let burst = Burst::new(2);
        assert_eq!(burst.push(0, 1), Pushed::First);
        assert_eq!(burst.push(1, 2), Pushed::Waits);
        assert_eq!(burst.push(0, 3), Pushed::Waits);
        burst.task_started();
        let mut seen = Vec::new();
        burst.take(|i, items| seen.push((i, std::mem::take(items))));
        assert_eq!(seen, [(0, vec![1, 3]), (1, vec![2])]);
        // Taken: nothing twice, and the next push starts a new burst.
        burst.take(|_, _| panic!("taken twice"));
        assert_eq!(burst.push(1, 4), Pushed::First);
    }

    #[test]
    fn a_full_burst_is_taken_at_once() {
        let burst = Burst::new(1);
        for n in 1..BURST_MAX {
            assert_ne!(burst.push(0, n), Pushed::Full, "item {n}");
        }
        assert_eq!(burst.push(0, BURST_MAX), Pushed::Full);
        let mut n = 0;
        burst.take(|_, items| n = items.len());
        assert_eq!(n, BURST_MAX);
    }

    /// Two threads push, two take: every shard's items come out in the order they went in,
    /// none lost, none twice.
    #[test]
    fn concurrent_bursts_keep_each_shards_order() {
        const N: usize = 20_000;
        let burst = Arc::new(Burst::new(2));
        let taken: Arc<Mutex<[Vec<usize>; 2]>> = Arc::default();
        let pusher = |shard: usize| {
            let (burst, taken) = (burst.clone(), taken.clone());
            std::thread::spawn(move || {
                for n in 0..N {
                    if burst.push(shard, n) != Pushed::Waits {
                        burst.task_started();
                        burst.take(|i, items| lock(&taken)[i].append(items));
                    }
                }
            })
        };
        let (a, b) = (pusher(0), pusher(1));
        a.join().expect("pusher 0");
        b.join().expect("pusher 1");
        burst.take(|i, items| lock(&taken)[i].append(items));
        let taken = lock(&taken);
        for (shard, items) in taken.iter().enumerate() {
            assert_eq!(*items, (0..N).collect::<Vec<_>>(), "shard {shard}");
        }
    }
}
