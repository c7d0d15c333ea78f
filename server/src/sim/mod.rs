//! The game of Diner Dash, ruleset `v0` (docs/rules.md): pure, synchronous and deterministic. It
//! knows nothing of sessions, networks or async; everything above it only calls this API.
//!
//! - [`config`]: the tunable numbers and their validation;
//! - [`rng`]: CPython-compatible MT19937 that draws arrival lists;
//! - [`restaurant`]: the state of one episode, the actions, time, observation and action mask;
//! - [`game`]: a restaurant plus its random stream: reset, checked step, snapshots;
//! - [`snapshot`]: the versioned binary format;
//! - [`render`]: the text board.

pub mod config;
pub mod game;
pub mod render;
pub mod restaurant;
pub mod rng;
pub mod snapshot;

pub use config::{Config, ConfigError, MAX_ARRIVALS};
pub use game::{Game, ResetInfo, StepError};
pub use restaurant::{
    ActionMask, ArrivalError, Group, NUM_ACTIONS, NUM_TABLES, OBSERVATION_SIZE, Observation,
    Restaurant, StateError, StepOutcome, TABLE_CAPACITIES,
};
pub use snapshot::{SNAPSHOT_VERSION, SnapshotError};

/// The ruleset this simulator implements.
pub const RULESET: &str = "v0";

/// Inclusive lower and upper bounds of each observation index (docs/rules.md §6).
pub fn observation_bounds() -> ([i8; OBSERVATION_SIZE], [i8; OBSERVATION_SIZE]) {
    let mut low = [0i8; OBSERVATION_SIZE];
    let mut high = [0i8; OBSERVATION_SIZE];
    for t in 0..NUM_TABLES {
        high[3 * t] = 6;
        high[3 * t + 1] = 6;
        low[3 * t + 2] = -1;
        high[3 * t + 2] = 4;
        high[18 + t] = 1;
    }
    for g in 0..7 {
        high[24 + 2 * g] = 4;
        high[25 + 2 * g] = 6;
    }
    high[38] = 18;
    high[39] = 18;
    (low, high)
}
