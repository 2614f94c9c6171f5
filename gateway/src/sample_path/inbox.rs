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
//!
//! **Correcting in place.** Handing every batch to a sleeping worker costs a wake-up, and at a
//! building's pace (a thousand sensors sending ten batches a second each) that hand-over was
//! about half of the gateway's CPU. So the receive thread may *claim* the inbox
//! ([`try_claim`](Inbox::try_claim)) and correct the batch itself, when the inbox is empty and
//! nobody else holds the claim; it then [`release`](Inbox::release)s. The worker claims too, for
//! each entry it takes ([`take_or_idle`](Inbox::take_or_idle)), so the two never handle a
//! shard's batches at once and never out of order: a batch is handled in place only when no
//! earlier one waits. How much of its time a receive thread may spend so is bounded by a
//! [`ReceiveBudget`]: under a heavy stream it hands the rest to the workers, which then correct
//! in parallel, and Zenoh's reading of the link is never held up for long.

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
    /// Someone (the worker or a receive thread) is handling an entry of this inbox's shard.
    claimed: bool,
}

/// What the inbox hands the worker.
#[derive(Debug, PartialEq, Eq)]
pub enum Next<T> {
    /// An entry to handle.
    Item(T),
    /// An entry left when the inbox closed, after its drain deadline: to be counted as dropped.
    Late(T),
    /// Closed and empty: the worker stops.
    Closed,
    /// Nothing came for the idle time given.
    Idle,
}

impl<T> Inbox<T> {
    /// `dropped` is shared so that all inboxes feed one counter.
    pub fn new(capacity: usize, dropped: Arc<AtomicU64>) -> Inbox<T> {
        Inbox {
            state: Mutex::new(State {
                queue: VecDeque::with_capacity(capacity.min(1024)),
                drain_until: None,
                claimed: false,
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
        // The worker waits on an empty queue, checked under the lock, or on a claimed one, which
        // `release` wakes it from: only the push that ends the emptiness needs to wake it, and
        // a wake costs a system call.
        if was_empty {
            self.ready.notify_one();
        }
    }

    /// Claims the inbox for handling one arrival in place: true when the inbox is open and
    /// empty, and unclaimed. The caller handles its entry and then calls
    /// [`release`](Self::release); on false it [`push`](Self::push)es the entry instead.
    pub fn try_claim(&self) -> bool {
        let mut s = self.lock();
        let free = s.drain_until.is_none() && s.queue.is_empty() && !s.claimed;
        s.claimed |= free;
        free
    }

    /// Ends a claim; wakes the worker if entries came meanwhile.
    pub fn release(&self) {
        let mut s = self.lock();
        s.claimed = false;
        if !s.queue.is_empty() || s.drain_until.is_some() {
            self.ready.notify_one();
        }
    }

    /// Waits for the next entry, or for the inbox to close.
    #[cfg(test)]
    pub fn pop(&self) -> Next<T> {
        self.pop_or_idle(None)
    }

    /// As [`pop`](Self::pop), but gives up with [`Next::Idle`] after `idle` with nothing to
    /// hand out, so that a worker whose sensors fell silent still does its housekeeping.
    #[cfg(test)]
    pub fn pop_or_idle(&self, idle: Option<std::time::Duration>) -> Next<T> {
        self.next(idle, false)
    }

    /// As `pop_or_idle` (in tests) for a worker that shares its shard with
    /// [`try_claim`](Self::try_claim): waits while the inbox is claimed, and claims it with
    /// every entry (or late entry) it hands out; the caller [`release`](Self::release)s.
    pub fn take_or_idle(&self, idle: Option<std::time::Duration>) -> Next<T> {
        self.next(idle, true)
    }

    fn next(&self, idle: Option<std::time::Duration>, claim: bool) -> Next<T> {
        let deadline = idle.map(|d| Instant::now() + d);
        let mut s = self.lock();
        loop {
            let available = !(claim && s.claimed);
            if let Some(item) = available.then(|| s.queue.pop_front()).flatten() {
                s.claimed |= claim;
                return match s.drain_until {
                    Some(deadline) if Instant::now() >= deadline => Next::Late(item),
                    _ => Next::Item(item),
                };
            }
            // Closed: done once nothing is queued and no claim is handling one.
            if s.drain_until.is_some() && s.queue.is_empty() && !(claim && s.claimed) {
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

    fn lock(&self) -> std::sync::MutexGuard<'_, State<T>> {
        // Push and pop cannot panic midway, so a poisoned queue is still a valid queue.
        self.state.lock().unwrap_or_else(|p| p.into_inner())
    }
}

/// How much of a receive thread's time correcting in place may take: a token bucket that
/// fills at [`Self::SHARE`] of the time passing, up to [`Self::BURST`], and that each batch
/// handled in place empties by the time it took. In place while there is credit left.
///
/// A building's pace (10 000 small batches a second at a few µs each: a few per cent of a
/// thread) stays inside it, so no batch wakes a worker, and a wake-up costs more than
/// correcting a small batch. A heavy stream (a hundred-sample batch every few µs) exhausts it
/// and goes to the workers, which correct in parallel while the receive thread goes on reading
/// the link: that thread is the one every stream of the link waits on.
#[derive(Debug, Clone, Copy)]
pub struct ReceiveBudget {
    credit_ns: i64,
    /// When `credit_ns` was last brought up to date; none: never used, full.
    updated: Option<Instant>,
}

impl ReceiveBudget {
    /// The share of the receive thread's time correction in place may take over time: an
    /// eighth.
    pub const SHARE: u32 = 8;
    /// In-place work a receive thread may do back to back after a rest (a burst of a few
    /// hundred small batches): the link's reading is held up about this long at most.
    pub const BURST: std::time::Duration = std::time::Duration::from_millis(1);

    pub const fn new() -> ReceiveBudget {
        ReceiveBudget {
            credit_ns: Self::BURST.as_nanos() as i64,
            updated: None,
        }
    }

    fn credit_at(&self, now: Instant) -> i64 {
        let burst_ns = Self::BURST.as_nanos() as i64;
        let Some(updated) = self.updated else {
            return burst_ns;
        };
        let earned_ns = now.saturating_duration_since(updated).as_nanos() / u128::from(Self::SHARE);
        let earned_ns = i64::try_from(earned_ns).unwrap_or(i64::MAX);
        self.credit_ns.saturating_add(earned_ns).min(burst_ns)
    }

    /// Whether a batch arriving `now` may be corrected in place.
    pub fn allows(&self, now: Instant) -> bool {
        self.credit_at(now) > 0
    }

    /// A batch was corrected in place from `started` until `ended`.
    pub fn spent(&mut self, started: Instant, ended: Instant) {
        let took_ns =
            i64::try_from(ended.saturating_duration_since(started).as_nanos()).unwrap_or(i64::MAX);
        self.credit_ns = self.credit_at(ended).saturating_sub(took_ns);
        self.updated = Some(ended);
    }
}

impl Default for ReceiveBudget {
    fn default() -> ReceiveBudget {
        ReceiveBudget::new()
    }
}

thread_local! {
    /// The budget of the receive thread this runs on (Zenoh's own threads, shared by every
    /// session of the process).
    static RECEIVE_BUDGET: std::cell::Cell<ReceiveBudget> =
        const { std::cell::Cell::new(ReceiveBudget::new()) };
}

/// Whether a batch arriving `now` may be corrected in place on this thread.
pub fn receive_budget_allows(now: Instant) -> bool {
    RECEIVE_BUDGET.get().allows(now)
}

/// Work done in place on this thread from `started` until `ended`: a batch corrected, or the
/// corrected batches of a burst published ([`super::outbox`]), which a worker would otherwise
/// have published.
pub fn receive_budget_spent(started: Instant, ended: Instant) {
    let mut budget = RECEIVE_BUDGET.get();
    budget.spent(started, ended);
    RECEIVE_BUDGET.set(budget);
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

    /// A claim in place and the worker's take never overlap, and an entry queued while the
    /// receive thread handles one in place waits for its release (order is kept).
    #[test]
    fn claims_serialise_the_receive_thread_and_the_worker() {
        let q = Arc::new(Inbox::<u32>::new(4, Arc::new(AtomicU64::new(0))));
        assert!(q.try_claim(), "empty and unclaimed");
        // A second arrival while claimed: queued.
        assert!(!q.try_claim());
        q.push(2);
        let q2 = q.clone();
        let worker = std::thread::spawn(move || q2.take_or_idle(Some(Duration::from_secs(5))));
        std::thread::sleep(Duration::from_millis(50));
        assert!(
            !worker.is_finished(),
            "the worker waits for the claim to end"
        );
        q.release();
        assert_eq!(worker.join().unwrap(), Next::Item(2));
        // The worker now holds the claim: no handling in place.
        assert!(!q.try_claim());
        q.release();
        assert!(q.try_claim(), "free again");
        q.release();
        // Not empty: queued behind what waits.
        q.push(3);
        assert!(!q.try_claim());
        assert_eq!(q.take_or_idle(None), Next::Item(3));
        q.release();
        // Closed: never in place.
        q.close(Instant::now() + Duration::from_secs(60));
        assert!(!q.try_claim());
        assert_eq!(q.take_or_idle(None), Next::Closed);
    }

    /// Work in place is allowed from rest up to about a burst, then at its share of the time.
    #[test]
    fn the_receive_budget_allows_a_burst_then_its_share() {
        let mut b = ReceiveBudget::new();
        let t0 = Instant::now();
        assert!(b.allows(t0));
        // Back to back batches of 100 µs each, with no time between them.
        let work = Duration::from_micros(100);
        let mut now = t0;
        let mut in_place = Duration::ZERO;
        while b.allows(now) {
            b.spent(now, now + work);
            now += work;
            in_place += work;
        }
        let burst = ReceiveBudget::BURST;
        assert!(in_place >= burst && in_place <= 2 * burst, "{in_place:?}");
        // Then at its share: one batch in eight, over a long stretch.
        let (mut allowed, n) = (0u32, 8000u32);
        for _ in 0..n {
            if b.allows(now) {
                b.spent(now, now + work);
                allowed += 1;
            }
            now += work;
        }
        let share = f64::from(allowed) / f64::from(n);
        assert!((share - 1.0 / 8.0).abs() < 0.01, "{share}");
        // Sparse small batches (5 µs every 100 µs: 5 %) are always allowed.
        let mut b = ReceiveBudget::new();
        for i in 0..10_000u32 {
            let at = t0 + Duration::from_micros(100) * i;
            assert!(b.allows(at), "batch {i}");
            b.spent(at, at + Duration::from_micros(5));
        }
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
