//! What the end-to-end benches share (`src/bin`: `triax-gateway-bench`, `triax-fleet-bench`;
//! BENCHMARKS.md has their methods and figures).

pub mod signal;
