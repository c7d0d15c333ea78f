//! The gRPC contract's files: `dinerdash/v1/dinerdash.proto` under [`DIR`], the single source of
//! truth for the server and the clients.
//!
//! A crate of its own so that the server's build script reaches the files through a (build)
//! dependency, which packaging carries along: maturin puts path dependencies into the
//! `dinerdash-server` sdist, while a plain `../proto` outside the server's package would be left
//! behind and the sdist would not build.

/// The include root of the contract: it holds `dinerdash/v1/dinerdash.proto`.
pub const DIR: &str = env!("CARGO_MANIFEST_DIR");

/// The contract's file, relative to [`DIR`].
pub const FILE: &str = "dinerdash/v1/dinerdash.proto";
