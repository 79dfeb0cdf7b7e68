//! wavesplat's local cluster and harnesses, shared by `wavesplat demo`, `wavesplat bench` and
//! the end-to-end tests, so that each starts servers, browses and scores the same way:
//! `console` (the spinner and the job table long commands show), `cluster` (the cache, orchestrator and worker wired on loopback in this process: the same
//! servers `wavesplat serve` and `wavesplat worker` run), `process` (the real `wavesplat` binary
//! started as a server, its address read from its first line), `postgres` (a throwaway
//! PostgreSQL server for the queue's tests and benches), `browse` (a frame loop fed by a
//! cache: the demo's and `bench refine`'s sessions, the backend probe, the scoring renderer's
//! settings), `scoring` (reference images of the original volume per view of a walk, Q_I and
//! SNR per frame), `report` (PNG charts and the offline `report.html`), `stability` (the stiff
//! and extreme numerical cases), `demo` (the demo's archive and report sections) and `refine`
//! (`bench refine`: the runs, records, CSV, charts and the paper's Table 4) and `throughput`
//! (`bench throughput`: the stages' speeds and the accumulation loop's ceiling). Errors are `anyhow`: this crate sits
//! at the binary's and the tests' edge, where errors are reported, not matched on.

pub mod browse;
pub mod cluster;
pub mod console;
pub mod demo;
pub mod postgres;
pub mod process;
pub mod refine;
pub mod report;
pub mod scoring;
pub mod stability;
pub mod throughput;

pub use cluster::{LocalCache, LocalStack};
