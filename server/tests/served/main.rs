//! The tests of a served server, in one test binary: each module talks to a server over real
//! sockets on 127.0.0.1, either one running inside the test's runtime (`grpc_support`) or the
//! real `dinerdash-server` binary (`binary_support`). Each module's docs say what it covers.
//!
//! One binary rather than one per file: as 18 binaries each built its own release copy of the
//! gRPC client and server code (20-40 s of CPU apiece, 680 s in all; 92 s as one, measured with
//! `cargo build --timings`). The test harness runs their tests two at a time, as it did each
//! file's. A module is run alone by its name: `cargo test --release -p dinerdash-server --test
//! served -- shm_doorbell::`.

mod binary_support;
mod grpc_support;
#[path = "../recorded/mod.rs"]
mod recorded;

mod binary_doors;
mod binary_drain;
mod binary_expose;
mod binary_fair;
mod binary_hostile;
mod binary_memory;
mod binary_operations;
mod binary_probes;
mod binary_restore;
mod binary_tenants;
mod grpc_concurrency;
mod grpc_error_details;
mod grpc_errors;
mod grpc_hostile;
mod grpc_lifecycle;
mod grpc_ops;
mod grpc_parallel;
mod grpc_planner;
mod grpc_step_stream;
mod http_pages;
mod metrics_golden;
mod shedding;
mod shm_doorbell;
