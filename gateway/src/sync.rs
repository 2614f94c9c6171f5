//! The one way the gateway takes a standard mutex.

use std::sync::{Mutex, MutexGuard};

/// The lock, whoever held it last: each value the gateway guards so is replaced whole, never
/// left half-written, so it is valid after a panic.
pub(crate) fn lock<T>(m: &Mutex<T>) -> MutexGuard<'_, T> {
    m.lock().unwrap_or_else(|p| p.into_inner())
}
