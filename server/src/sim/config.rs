//! The game's tunable numbers: ruleset `v0` defaults, and their validation.
//!
//! Everything that docs/rules.md §9 lets a user change lives here; table layout and the sizes of the
//! observation and action spaces do not.

use serde::{Deserialize, Serialize};

/// Longest arrival list a game holds (docs/rules.md §2 draws exactly this many).
pub const MAX_ARRIVALS: usize = 200;

/// A configuration value outside its allowed range.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("{field} must be in {min}..={max}, got {value}")]
pub struct ConfigError {
    /// The configuration field, as named in the protocol (`patience_type1`, ...).
    pub field: &'static str,
    /// The value that was given.
    pub value: u32,
    /// Smallest allowed value.
    pub min: u32,
    /// Largest allowed value.
    pub max: u32,
}

/// The numbers of one game. `Config::default()` is ruleset `v0`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct Config {
    /// After an arrival at tick `now`, the next one waits until a tick greater than
    /// `now + arrival_interval` (8: arrivals at 0, 9, 18, ...).
    pub arrival_interval: u32,
    /// Initial patience `P` of customer types 1 and 2.
    pub patience: [u32; 2],
    /// Patience decay `d` per tick of customer types 1 and 2.
    pub decay: [u32; 2],
    /// Ticks from seating until a group is ready to order.
    pub reading_ticks: u32,
    /// Ticks an order stays in the kitchen before its food comes out.
    pub cooking_ticks: u32,
    /// Ticks from serving until a group asks for the bill.
    pub eating_ticks: u32,
    /// Groups lost before the episode terminates.
    pub lives: u32,
    /// Steps after which the episode is truncated; 0 means no limit (the reference has none).
    pub time_limit: u32,
}

impl Default for Config {
    fn default() -> Self {
        Config {
            arrival_interval: 8,
            patience: [600, 800],
            decay: [12, 7],
            reading_ticks: 10,
            cooking_ticks: 10,
            eating_ticks: 10,
            lives: 5,
            time_limit: 0,
        }
    }
}

impl Config {
    /// Checks every field against its range; the first field out of range is the error.
    ///
    /// Patience stays below 1000 so that the observation's patience level (`P div 200`) keeps
    /// within the published bounds 0..=4.
    pub fn validate(&self) -> Result<(), ConfigError> {
        let check = |field, value: u32, min, max| {
            if (min..=max).contains(&value) {
                Ok(())
            } else {
                Err(ConfigError {
                    field,
                    value,
                    min,
                    max,
                })
            }
        };
        check("arrival_interval", self.arrival_interval, 1, 1000)?;
        check("patience_type1", self.patience[0], 1, 999)?;
        check("patience_type2", self.patience[1], 1, 999)?;
        check("decay_type1", self.decay[0], 0, 1000)?;
        check("decay_type2", self.decay[1], 0, 1000)?;
        check("reading_ticks", self.reading_ticks, 0, 1000)?;
        check("cooking_ticks", self.cooking_ticks, 0, 1000)?;
        check("eating_ticks", self.eating_ticks, 0, 1000)?;
        check("lives", self.lives, 1, 1000)?;
        check("time_limit", self.time_limit, 0, u32::MAX)?;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn default_is_valid_v0() {
        let c = Config::default();
        assert_eq!(c.validate(), Ok(()));
        assert_eq!(c.patience, [600, 800]);
        assert_eq!(c.decay, [12, 7]);
    }

    #[test]
    fn out_of_range_names_the_field() {
        let c = Config {
            patience: [600, 1000],
            ..Config::default()
        };
        let e = c.validate().unwrap_err();
        assert_eq!(e.field, "patience_type2");
        assert_eq!(e.to_string(), "patience_type2 must be in 1..=999, got 1000");
    }
}
