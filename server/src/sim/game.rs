//! A game: the restaurant of the current episode plus the random stream that draws each
//! episode's arrival list (docs/rules.md §2, §3), reset, checked stepping, and snapshots.

use serde::{Deserialize, Serialize};

use super::config::{Config, ConfigError, MAX_ARRIVALS};
use super::restaurant::{
    ArrivalError, NUM_ACTIONS, Restaurant, StateError, StepOutcome, pack_arrivals,
};
use super::rng::Mt19937;
use super::snapshot::{self, SnapshotError};

/// Why a step was refused.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum StepError {
    /// The action is not one of the 57.
    #[error("action must be in 0..=56, got {0}")]
    ActionOutOfRange(i64),
    /// The game has never been reset.
    #[error("the game was never reset; call reset")]
    NotReset,
}

/// Which random stream an episode's arrivals came from, so that it can be replayed.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ResetInfo {
    /// Seed of the random stream: `reset(Some(seed))` starts it again.
    pub seed: u64,
    /// Resets of this stream since it was seeded, not counting this one: after
    /// `reset(Some(seed))`, this many unseeded resets replay the episode.
    pub stream_episodes: u32,
}

/// One Diner Dash game. Cloning copies everything, random stream included.
#[derive(Debug, Clone, PartialEq, Eq, Serialize, Deserialize)]
pub struct Game {
    /// The current episode.
    restaurant: Restaurant,
    /// Configuration for the next reset (the restaurant keeps the one it was reset with).
    config: Config,
    /// The arrival generator; `None` until the first reset.
    rng: Option<Mt19937>,
    /// Seed that started `rng`.
    seed: u64,
    /// Arrival lists drawn from `rng` since it was seeded.
    stream_episodes: u32,
    /// Whether an episode has started (`reset` was called).
    started: bool,
}

impl Game {
    /// A game with the given configuration, not reset yet.
    pub fn new(config: Config) -> Result<Game, ConfigError> {
        config.validate()?;
        let (arrivals, len) = pack_arrivals(&[(1, 1)]).unwrap_or(([0x11; MAX_ARRIVALS], 1));
        Ok(Game {
            restaurant: Restaurant::new(config, arrivals, len),
            config,
            rng: None,
            seed: 0,
            stream_episodes: 0,
            started: false,
        })
    }

    /// Uses `config` from the next reset on.
    pub fn set_config(&mut self, config: Config) -> Result<(), ConfigError> {
        config.validate()?;
        self.config = config;
        Ok(())
    }

    /// The configuration of the next reset.
    pub fn config(&self) -> &Config {
        &self.config
    }

    /// Starts an episode (docs/rules.md §3). With a seed the random stream restarts from it; without
    /// one it continues (a game never seeded starts from seed 0: the simulator draws no entropy,
    /// so callers that want a fresh game draw a seed themselves, as sessions do). An explicit
    /// arrival list replaces the drawn one and consumes no random numbers.
    pub fn reset(
        &mut self,
        seed: Option<u64>,
        arrivals: Option<&[(u32, u32)]>,
    ) -> Result<ResetInfo, ArrivalError> {
        let explicit = arrivals.map(pack_arrivals).transpose()?;
        if let Some(seed) = seed {
            self.rng = Some(Mt19937::from_seed(seed));
            self.seed = seed;
            self.stream_episodes = 0;
        }
        let rng = self.rng.get_or_insert_with(|| {
            self.seed = 0;
            self.stream_episodes = 0;
            Mt19937::from_seed(0)
        });
        let info = ResetInfo {
            seed: self.seed,
            stream_episodes: self.stream_episodes,
        };
        let (list, len) = match explicit {
            Some(packed) => packed,
            None => {
                let mut draws = [[0u32; 2]; MAX_ARRIVALS];
                rng.uniform_pairs([(1, 2), (1, 6)], &mut draws);
                let mut list = [0u8; MAX_ARRIVALS];
                for (entry, [customer_type, size]) in list.iter_mut().zip(draws) {
                    *entry = (customer_type << 4 | size) as u8;
                }
                self.stream_episodes += 1;
                (list, MAX_ARRIVALS as u8)
            }
        };
        self.restaurant = Restaurant::new(self.config, list, len);
        self.started = true;
        Ok(info)
    }

    /// One step; refuses actions outside 0..=56 and games never reset.
    pub fn step(&mut self, action: i64) -> Result<StepOutcome, StepError> {
        if !self.started {
            return Err(StepError::NotReset);
        }
        if !(0..NUM_ACTIONS as i64).contains(&action) {
            return Err(StepError::ActionOutOfRange(action));
        }
        Ok(self.restaurant.step(action as u8))
    }

    /// The seed of the random stream and how many arrival lists it has drawn since: together
    /// they name the current episode, so a policy that needs randomness of its own (the planner)
    /// seeds it from them and replays with the episode.
    pub fn stream_position(&self) -> (u64, u32) {
        (self.seed, self.stream_episodes)
    }

    /// Whether the random stream was ever seeded (by a reset).
    pub fn is_seeded(&self) -> bool {
        self.rng.is_some()
    }

    /// Whether `reset` has been called.
    pub fn is_started(&self) -> bool {
        self.started
    }

    /// The current episode.
    pub fn restaurant(&self) -> &Restaurant {
        &self.restaurant
    }

    /// A versioned binary snapshot of the whole game, random stream included.
    pub fn snapshot(&self) -> Vec<u8> {
        snapshot::encode(snapshot::GAME, self)
    }

    /// The game a [`Game::snapshot`] was taken of.
    pub fn restore(bytes: &[u8]) -> Result<Game, SnapshotError> {
        let game: Game = snapshot::decode(snapshot::GAME, bytes)?;
        game.check()?;
        Ok(game)
    }

    /// Checks a deserialised game for states no sequence of steps can produce.
    pub fn check(&self) -> Result<(), StateError> {
        self.config
            .validate()
            .map_err(|_| StateError("configuration out of range"))?;
        if self.rng.as_ref().is_some_and(|r| !r.is_consistent()) {
            return Err(StateError("random stream"));
        }
        // Counted up by each drawn arrival list; the maximum could not be counted past.
        if self.stream_episodes == u32::MAX {
            return Err(StateError("random stream episodes"));
        }
        self.restaurant.check()
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn unseeded_reset_reports_a_seed_that_replays() {
        let mut a = Game::new(Config::default()).unwrap();
        let info = a.reset(None, None).unwrap();
        assert_eq!(info.stream_episodes, 0);
        let mut b = Game::new(Config::default()).unwrap();
        b.reset(Some(info.seed), None).unwrap();
        assert_eq!(a.restaurant(), b.restaurant());
        // The next unseeded reset continues the stream; seed + 1 more reset replays it.
        let next = a.reset(None, None).unwrap();
        assert_eq!(
            next,
            ResetInfo {
                seed: info.seed,
                stream_episodes: 1
            }
        );
        let mut c = Game::new(Config::default()).unwrap();
        c.reset(Some(info.seed), None).unwrap();
        c.reset(None, None).unwrap();
        assert_eq!(a.restaurant(), c.restaurant());
        assert_ne!(a.restaurant(), b.restaurant());
    }

    #[test]
    fn explicit_arrivals_consume_no_random_numbers() {
        let mut a = Game::new(Config::default()).unwrap();
        a.reset(Some(5), None).unwrap();
        a.reset(None, Some(&[(2, 3), (1, 1)])).unwrap();
        assert_eq!(
            a.restaurant().arrivals().collect::<Vec<_>>(),
            vec![(2, 3), (1, 1)]
        );
        a.reset(None, None).unwrap();
        let mut b = Game::new(Config::default()).unwrap();
        b.reset(Some(5), None).unwrap();
        b.reset(None, None).unwrap();
        assert_eq!(a.restaurant(), b.restaurant());
    }

    #[test]
    fn refuses_bad_actions_and_unreset_games() {
        let mut g = Game::new(Config::default()).unwrap();
        assert_eq!(g.step(0), Err(StepError::NotReset));
        g.reset(Some(1), None).unwrap();
        assert_eq!(g.step(57), Err(StepError::ActionOutOfRange(57)));
        assert_eq!(
            g.step(-1).unwrap_err().to_string(),
            "action must be in 0..=56, got -1"
        );
        assert!(g.step(56).is_ok());
    }

    #[test]
    fn bad_arrivals_are_errors() {
        let mut g = Game::new(Config::default()).unwrap();
        assert_eq!(g.reset(None, Some(&[])), Err(ArrivalError::Length(0)));
        assert!(matches!(
            g.reset(None, Some(&[(1, 1), (3, 1)])),
            Err(ArrivalError::Group { index: 1, .. })
        ));
    }

    #[test]
    fn snapshot_restores_and_rejects_garbage() {
        let mut g = Game::new(Config::default()).unwrap();
        g.reset(Some(9), None).unwrap();
        for a in [15, 0, 0, 1] {
            g.step(a).unwrap();
        }
        let bytes = g.snapshot();
        assert_eq!(Game::restore(&bytes).unwrap(), g);
        assert!(Game::restore(&bytes[..bytes.len() / 2]).is_err());
        assert!(Game::restore(b"nonsense").is_err());
    }
}
