//! The gRPC contract: `proto/dinerdash/v1/dinerdash.proto`, the single source of truth for the
//! server and the clients.
//!
//! A crate of its own so that packaging carries the contract along with the server: maturin puts
//! the server's path dependencies into the `dinerdash-server` sdist, and a plain `../proto` outside
//! the server's package would be left behind (the sdist would not build). The server's build
//! script finds the files beside its own package (`../proto`) at build time, not through a path
//! compiled into this crate, which a target directory shared by two clones would make stale.

/// The contract's file, relative to the `proto/` folder (the include root).
pub const FILE: &str = "dinerdash/v1/dinerdash.proto";
