//! The tests of a served server, in one test binary: each module talks to a server over real
//! sockets on 127.0.0.1, either one running inside the test's runtime (`grpc_support`) or the
//! real `dinerdash-server` binary (`binary_support`). Each module's docs say what it covers.
//!
//! One binary rather than one per file: each of these linked its own copy of the gRPC client and
//! server code, built in release ~40 s apiece (18 of them, about 7 min of a 2-core machine's
//! clean build); built once here they take a fraction of that. The test harness runs them two at
//! a time as before. A module is run alone by its name: `cargo test --release -p
//! dinerdash-server --test served -- shm_doorbell::`.

mod binary_support;
mod grpc_support;
#[path = "../recorded/mod.rs"]
mod recorded;

mod binary_drain;
mod binary_expose;
mod binary_hostile;
mod binary_memory;
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
