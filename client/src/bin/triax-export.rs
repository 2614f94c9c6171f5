//! `triax-export`: a building's history, read from its gateway over Zenoh, written to files
//! for analysis tools; everything is in [`triax_client::export`].
//!
//! ```text
//! triax-export parquet --connect tcp/127.0.0.1:7447 --building hq --sensor acc-01 \
//!     --from 2026-11-24T00:00:00Z --to 2026-11-25T00:00:00Z --out acc-01.parquet
//! triax-export sds --connect tcp/127.0.0.1:7447 --building hq --out archive --records records/
//! ```

use std::process::ExitCode;

#[tokio::main(flavor = "multi_thread", worker_threads = 2)]
async fn main() -> ExitCode {
    tracing_subscriber::fmt()
        .with_env_filter(
            tracing_subscriber::EnvFilter::try_from_env("TRIAX_LOG")
                // Zenoh's own warnings name its source files; the export's error names the
                // endpoint and the cause (TRIAX_LOG=zenoh=warn shows them).
                .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("warn,zenoh=error")),
        )
        .with_writer(std::io::stderr)
        .init();
    ExitCode::from(triax_client::export::main(std::env::args_os()).await)
}
