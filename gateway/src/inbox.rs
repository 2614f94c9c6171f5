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
//! A std mutex and not a tokio one: it is held only for a push or a pop, never across an await.

use std::collections::VecDeque;
use std::sync::atomic::{AtomicU64, Ordering::Relaxed};
use std::sync::{Arc, Mutex};

use tokio::sync::Notify;

#[derive(Debug)]
pub struct Inbox<T> {
    queue: Mutex<VecDeque<T>>,
    capacity: usize,
    notify: Notify,
    dropped: Arc<AtomicU64>,
}

impl<T> Inbox<T> {
    /// `dropped` is shared so that all inboxes feed one counter.
    pub fn new(capacity: usize, dropped: Arc<AtomicU64>) -> Inbox<T> {
        Inbox {
            queue: Mutex::new(VecDeque::with_capacity(capacity.min(1024))),
            capacity: capacity.max(1),
            notify: Notify::new(),
            dropped,
        }
    }

    /// Enqueues `item`, dropping the oldest entry if the queue is full. Never blocks beyond the
    /// short critical section.
    pub fn push(&self, item: T) {
        let was_empty = {
            let mut q = self.lock();
            let was_empty = q.is_empty();
            if q.len() >= self.capacity {
                q.pop_front();
                self.dropped.fetch_add(1, Relaxed);
            }
            q.push_back(item);
            was_empty
        };
        // Only the push that makes the queue non-empty wakes the worker: until the worker has
        // found the queue empty again it pops without waiting, so later pushes need no wake.
        if was_empty {
            self.notify.notify_one();
        }
    }

    pub fn try_pop(&self) -> Option<T> {
        self.lock().pop_front()
    }

    /// Waits for the next entry.
    pub async fn pop(&self) -> T {
        loop {
            if let Some(item) = self.try_pop() {
                return item;
            }
            // notify_one stores a permit when no one waits, so a push between try_pop and
            // here is not lost.
            self.notify.notified().await;
        }
    }

    pub fn len(&self) -> usize {
        self.lock().len()
    }

    pub fn is_empty(&self) -> bool {
        self.len() == 0
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, VecDeque<T>> {
        // Push and pop cannot panic midway, so a poisoned queue is still a valid queue.
        self.queue.lock().unwrap_or_else(|p| p.into_inner())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn drops_oldest_and_counts() {
        let dropped = Arc::new(AtomicU64::new(0));
        let q = Inbox::new(3, dropped.clone());
        for i in 0..5 {
            q.push(i);
        }
        assert_eq!(dropped.load(Relaxed), 2);
        assert_eq!(q.len(), 3);
        assert_eq!(q.try_pop(), Some(2));
    }

    #[tokio::test]
    async fn pop_waits_for_a_push() {
        let q = Arc::new(Inbox::new(2, Arc::new(AtomicU64::new(0))));
        let q2 = q.clone();
        let t = tokio::spawn(async move { q2.pop().await });
        tokio::task::yield_now().await;
        q.push(7);
        assert_eq!(t.await.unwrap(), 7);
    }
}
