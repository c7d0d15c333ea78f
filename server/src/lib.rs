//! DinerDash Gym server: the Diner Dash benchmark's game, its reference expert, and the gRPC
//! environment service that hosts many sessions of it.
//!
//! # Layout
//! - [`sim`]: the game itself, pure and synchronous (RULES.md).
//! - [`expert`]: policies that read the game: the reference heuristic, random.
//! - [`eval`]: runs a policy over many episodes and summarises scores (the `eval` command).

pub mod eval;
pub mod expert;
pub mod sim;
