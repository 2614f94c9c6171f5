//! A bounded queue between the Zenoh receive callback and a correction worker that drops the
//! oldest entry when full, and counts what it dropped.
//!
//! Zenoh calls the subscriber callback on its own receive threads, and a stalled callback stalls
//! every stream on the link. Under the drop-oldest policy (the default) the callback only pushes
//! here, and when a worker falls behind (a slow consumer, a burst) the stalest batch goes
//! first: live monitoring values fresh data over complete data, and the gap shows downstream as
//! a `sequence_gap` flag plus the `dropped` counter. (Under backpressure there is no inbox: the
//! stall is the point, see [`crate::config::Overload`].)
//!
//! The worker is a thread of its own and waits here on a condition variable: it blocks
//! whenever a consumer is slow (publishing waits for room), which must not take a thread from
//! the async runtime that serves status, metrics and calibration pushes.

use std::collections::VecDeque;
use std::sync::atomic::{AtomicU64, Ordering::Relaxed};
use std::sync::{Arc, Condvar, Mutex};
use std::time::Instant;

#[derive(Debug)]
pub struct Inbox<T> {
    state: Mutex<State<T>>,
    capacity: usize,
    ready: Condvar,
    dropped: Arc<AtomicU64>,
}

#[derive(Debug)]
struct State<T> {
    queue: VecDeque<T>,
    /// Set by [`Inbox::close`]: what is still queued is to be taken until then, and dropped
    /// (counted) after.
    drain_until: Option<Instant>,
}

/// What [`Inbox::pop`] hands the worker.
#[derive(Debug, PartialEq, Eq)]
pub enum Next<T> {
    /// An entry to handle.
    Item(T),
    /// An entry left when the inbox closed, after its drain deadline: to be counted as dropped.
    Late(T),
    /// Closed and empty: the worker stops.
    Closed,
    /// Nothing came for the time given to [`Inbox::pop_or_idle`].
    Idle,
}

impl<T> Inbox<T> {
    /// `dropped` is shared so that all inboxes feed one counter.
    pub fn new(capacity: usize, dropped: Arc<AtomicU64>) -> Inbox<T> {
        Inbox {
            state: Mutex::new(State {
                queue: VecDeque::with_capacity(capacity.min(1024)),
                drain_until: None,
            }),
            capacity: capacity.max(1),
            ready: Condvar::new(),
            dropped,
        }
    }

    /// Enqueues `item`, dropping the oldest entry if the queue is full. Never blocks beyond the
    /// short critical section. After [`close`](Self::close) the item is dropped and counted:
    /// its worker may have stopped.
    pub fn push(&self, item: T) {
        let was_empty = {
            let mut s = self.lock();
            if s.drain_until.is_some() {
                self.dropped.fetch_add(1, Relaxed);
                return;
            }
            let was_empty = s.queue.is_empty();
            if s.queue.len() >= self.capacity {
                s.queue.pop_front();
                self.dropped.fetch_add(1, Relaxed);
            }
            s.queue.push_back(item);
            was_empty
        };
        // The worker waits only on an empty queue, checked under the lock, so only the push
        // that ends the emptiness needs to wake it: a wake costs a system call.
        if was_empty {
            self.ready.notify_one();
        }
    }

    /// Waits for the next entry, or for the inbox to close.
    pub fn pop(&self) -> Next<T> {
        self.pop_or_idle(None)
    }

    /// As [`pop`](Self::pop), but gives up with [`Next::Idle`] after `idle` with nothing to
    /// hand out, so that a worker whose sensors fell silent still does its housekeeping.
    pub fn pop_or_idle(&self, idle: Option<std::time::Duration>) -> Next<T> {
        let deadline = idle.map(|d| Instant::now() + d);
        let mut s = self.lock();
        loop {
            if let Some(item) = s.queue.pop_front() {
                return match s.drain_until {
                    Some(deadline) if Instant::now() >= deadline => Next::Late(item),
                    _ => Next::Item(item),
                };
            }
            if s.drain_until.is_some() {
                return Next::Closed;
            }
            s = match deadline {
                None => self.ready.wait(s).unwrap_or_else(|p| p.into_inner()),
                Some(deadline) => {
                    let left = deadline.saturating_duration_since(Instant::now());
                    if left.is_zero() {
                        return Next::Idle;
                    }
                    self.ready
                        .wait_timeout(s, left)
                        .unwrap_or_else(|p| p.into_inner())
                        .0
                }
            };
        }
    }

    /// No more pushes will come: the worker takes what is queued until `drain_until`, is
    /// handed the rest as [`Next::Late`], then gets [`Next::Closed`].
    pub fn close(&self, drain_until: Instant) {
        self.lock().drain_until = Some(drain_until);
        self.ready.notify_all();
    }

    pub fn len(&self) -> usize {
        self.lock().queue.len()
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, State<T>> {
        // Push and pop cannot panic midway, so a poisoned queue is still a valid queue.
        self.state.lock().unwrap_or_else(|p| p.into_inner())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::time::Duration;

    #[test]
    fn drops_oldest_and_counts() {
        let dropped = Arc::new(AtomicU64::new(0));
        let q = Inbox::new(3, dropped.clone());
        for i in 0..5 {
            q.push(i);
        }
        assert_eq!(dropped.load(Relaxed), 2);
        assert_eq!(q.len(), 3);
        assert_eq!(q.pop(), Next::Item(2));
    }

    #[test]
    fn pop_waits_for_a_push() {
        let q = Arc::new(Inbox::new(2, Arc::new(AtomicU64::new(0))));
        let q2 = q.clone();
        let t = std::thread::spawn(move || q2.pop());
        std::thread::sleep(Duration::from_millis(50));
        q.push(7);
        assert_eq!(t.join().unwrap(), Next::Item(7));
    }

    #[test]
    fn an_empty_inbox_says_idle_after_the_time_given_and_an_item_still_comes_first() {
        let q = Inbox::<u32>::new(2, Arc::new(AtomicU64::new(0)));
        let started = Instant::now();
        assert_eq!(q.pop_or_idle(Some(Duration::from_millis(30))), Next::Idle);
        assert!(started.elapsed() >= Duration::from_millis(30));
        q.push(3);
        assert_eq!(q.pop_or_idle(Some(Duration::ZERO)), Next::Item(3));
    }

    #[test]
    fn close_wakes_the_worker_and_hands_over_what_is_left() {
        let q = Arc::new(Inbox::<u32>::new(4, Arc::new(AtomicU64::new(0))));
        let q2 = q.clone();
        let waiting = std::thread::spawn(move || q2.pop());
        std::thread::sleep(Duration::from_millis(50));
        q.close(Instant::now() + Duration::from_secs(60));
        assert_eq!(waiting.join().unwrap(), Next::Closed);

        let q = Inbox::new(4, Arc::new(AtomicU64::new(0)));
        q.push(1);
        q.push(2);
        q.close(Instant::now() + Duration::from_secs(60));
        assert_eq!(q.pop(), Next::Item(1));
        assert_eq!(q.pop(), Next::Item(2));
        assert_eq!(q.pop(), Next::Closed);
        let q = Inbox::new(4, Arc::new(AtomicU64::new(0)));
        q.push(1);
        q.close(Instant::now());
        assert_eq!(q.pop(), Next::Late(1));
        assert_eq!(q.pop(), Next::Closed);
    }

    #[test]
    fn a_push_after_close_is_counted_as_dropped() {
        let dropped = Arc::new(AtomicU64::new(0));
        let q = Inbox::new(4, dropped.clone());
        q.close(Instant::now() + Duration::from_secs(60));
        q.push(1);
        assert_eq!(dropped.load(Relaxed), 1);
        assert_eq!(q.pop(), Next::Closed);
    }
}
