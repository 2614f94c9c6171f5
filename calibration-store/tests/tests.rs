//! Integration tests of the calibration store, one binary.
//!
//! - `util`: shared helpers (records, temporary stores, raw sled access for corruption).
//! - `put`: validation and the version rules of `put`.
//! - `reads`: current, in force at a time, history, list, newer-than.
//! - `damage`: schema version, corrupt entries, the process lock.
//! - `transfer`: export and import.
//! - `cli`: the `store` subcommands, parsed and run.
//! - `crash`: `kill -9` of a writing child process at random moments.

mod cli;
mod crash;
mod damage;
mod put;
mod reads;
mod transfer;
mod util;
