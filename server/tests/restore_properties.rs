//! Restore refuses what the game cannot reach (issue 12): any snapshot it accepts, however it was
//! mangled, stays inside the Spec's observation bounds for 1,000 random steps (with autoreset, as
//! a session plays) and can be snapshotted and restored again. Each property also counts its
//! verdicts: a fair share of the mangled snapshots must get past Restore (or the property checks
//! nothing) and a fair share must be refused (or Restore checks nothing).

use std::sync::atomic::{AtomicUsize, Ordering};

use dinerdash_server::sim::{Config, Game, NUM_ACTIONS, observation_bounds};
use proptest::prelude::*;
use proptest::test_runner::TestRunner;
use serde_json::Value;

fn config() -> impl Strategy<Value = Config> {
    (
        1u32..20,
        (1u32..1000, 1u32..1000),
        (0u32..40, 0u32..40),
        (0u32..20, 0u32..20, 0u32..20),
        1u32..8,
        prop_oneof![Just(0u32), 1u32..400],
    )
        .prop_map(
            |(arrival_interval, (p1, p2), (d1, d2), (reading, cooking, eating), lives, limit)| {
                Config {
                    arrival_interval,
                    patience: [p1, p2],
                    decay: [d1, d2],
                    reading_ticks: reading,
                    cooking_ticks: cooking,
                    eating_ticks: eating,
                    lives,
                    time_limit: limit,
                }
            },
        )
}

/// A game after `warm` random steps.
fn played(config: Config, seed: u64, warm: &[u8]) -> Game {
    let mut game = Game::new(config).unwrap();
    game.reset(Some(seed), None).unwrap();
    for &a in warm {
        let r = game.restaurant();
        if r.is_terminated() || r.is_truncated() {
            break;
        }
        game.step(i64::from(a)).unwrap();
    }
    game
}

/// Values a hostile client would try in a numeric field.
fn nasty() -> impl Strategy<Value = i64> {
    prop_oneof![
        Just(0),
        Just(1),
        Just(-1),
        Just(i64::from(i32::MAX)),
        Just(i64::from(i32::MIN)),
        Just(1 << 30),
        Just(i64::from(u32::MAX)),
        -1000i64..5000,
    ]
}

/// The numeric leaves of a JSON value, as paths of indices.
fn leaves(v: &Value, path: &mut Vec<String>, out: &mut Vec<Vec<String>>) {
    match v {
        Value::Number(_) => out.push(path.clone()),
        Value::Array(items) => {
            for (i, item) in items.iter().enumerate() {
                path.push(i.to_string());
                leaves(item, path, out);
                path.pop();
            }
        }
        Value::Object(map) => {
            for (k, item) in map {
                path.push(k.clone());
                leaves(item, path, out);
                path.pop();
            }
        }
        _ => {}
    }
}

fn leaf_mut<'a>(v: &'a mut Value, path: &[String]) -> &'a mut Value {
    path.iter().fold(v, |v, key| match v {
        Value::Array(items) => &mut items[key.parse::<usize>().unwrap()],
        Value::Object(map) => map.get_mut(key).unwrap(),
        _ => unreachable!(),
    })
}

/// Snapshot bytes of `game` with some numeric fields set to `values`; `None` when the values do
/// not even fit the fields' types.
fn mangled_fields(game: &Game, picks: &[(usize, i64)]) -> Option<Vec<u8>> {
    let mut v = serde_json::to_value(game).unwrap();
    let mut paths = Vec::new();
    leaves(&v, &mut Vec::new(), &mut paths);
    for &(pick, value) in picks {
        let path = &paths[pick % paths.len()];
        *leaf_mut(&mut v, path) = Value::from(value);
    }
    serde_json::from_value::<Game>(v).ok().map(|g| g.snapshot())
}

/// Plays 1,000 steps from a restored game as a session would (reset when an episode ends),
/// checking the observation bounds, then snapshots and restores it again.
fn stays_in_bounds(mut game: Game, actions: &[u8]) -> Result<(), TestCaseError> {
    let (low, high) = observation_bounds();
    for &a in actions {
        let r = game.restaurant();
        let obs = r.observation();
        for i in 0..obs.len() {
            prop_assert!(
                (low[i]..=high[i]).contains(&obs[i]),
                "observation[{}] = {} outside {}..={}",
                i,
                obs[i],
                low[i],
                high[i]
            );
        }
        if !game.is_started() || r.is_terminated() || r.is_truncated() {
            game.reset(None, None).unwrap();
        } else {
            game.step(i64::from(a)).unwrap();
        }
    }
    let again = Game::restore(&game.snapshot());
    prop_assert!(again.is_ok(), "its own snapshot refused: {:?}", again.err());
    Ok(())
}

/// How many cases Restore accepted and refused, for the bounds that make the properties mean
/// something: a Restore that refused everything would pass "every accepted snapshot stays in
/// bounds" without checking anything, and one that accepted everything would check no refusal.
#[derive(Debug, Default)]
struct Verdicts {
    accepted: AtomicUsize,
    refused: AtomicUsize,
}

impl Verdicts {
    /// Counts `restored` and plays it on when accepted.
    fn judge(
        &self,
        restored: Result<Game, impl std::fmt::Debug>,
        actions: &[u8],
    ) -> Result<(), TestCaseError> {
        match restored {
            Ok(game) => {
                self.accepted.fetch_add(1, Ordering::Relaxed);
                stays_in_bounds(game, actions)
            }
            Err(_) => {
                self.refused.fetch_add(1, Ordering::Relaxed);
                Ok(())
            }
        }
    }

    /// At least `accepted_min` cases were accepted and `refused_min` refused.
    #[track_caller]
    fn at_least(&self, accepted_min: usize, refused_min: usize) {
        let (accepted, refused) = (
            self.accepted.load(Ordering::Relaxed),
            self.refused.load(Ordering::Relaxed),
        );
        eprintln!("{accepted} accepted, {refused} refused of {CASES} cases");
        assert!(
            accepted >= accepted_min && refused >= refused_min,
            "{accepted} accepted and {refused} refused of {CASES} cases: want at least \
             {accepted_min} and {refused_min}"
        );
    }
}

/// Cases of each property.
const CASES: u32 = 256;

fn runner() -> TestRunner {
    TestRunner::new(ProptestConfig {
        cases: CASES,
        source_file: Some(file!()),
        ..ProptestConfig::default()
    })
}

#[test]
fn accepted_mangled_fields_stay_in_bounds() {
    let verdicts = Verdicts::default();
    let cases = (
        config(),
        any::<u64>(),
        prop::collection::vec(0u8..NUM_ACTIONS as u8, 0..300),
        prop::collection::vec((any::<usize>(), nasty()), 1..4),
        prop::collection::vec(0u8..NUM_ACTIONS as u8, 1000),
    );
    runner()
        .run(&cases, |(config, seed, warm, picks, actions)| {
            let game = played(config, seed, &warm);
            // Values that do not fit a field's type never reach Restore.
            match mangled_fields(&game, &picks) {
                Some(bytes) => verdicts.judge(Game::restore(&bytes), &actions),
                None => Ok(()),
            }
        })
        .unwrap();
    // Measured over 30 runs: 67 to 93 accepted, 14 to 30 refused of the 256 cases (most values
    // do not fit their field's type). The bounds are far in the tails of those counts.
    verdicts.at_least(32, 4);
}

#[test]
fn accepted_flipped_bytes_stay_in_bounds() {
    let verdicts = Verdicts::default();
    let cases = (
        config(),
        any::<u64>(),
        prop::collection::vec(0u8..NUM_ACTIONS as u8, 0..300),
        prop::collection::vec((any::<usize>(), any::<u8>()), 1..4),
        prop::collection::vec(0u8..NUM_ACTIONS as u8, 1000),
    );
    runner()
        .run(&cases, |(config, seed, warm, flips, actions)| {
            let mut bytes = played(config, seed, &warm).snapshot();
            // Past the kind tag and version, which are checked first anyway.
            let body = bytes.len() - 6;
            for (at, value) in flips {
                bytes[6 + at % body] = value;
            }
            verdicts.judge(Game::restore(&bytes), &actions)
        })
        .unwrap();
    // Measured over 30 runs: 39 to 63 accepted, 193 to 217 refused of the 256 cases. The
    // bounds are far in the tails of those counts.
    verdicts.at_least(16, 64);
}

/// States of the report: a patience of 2^31 - 1, a clock past the longest episode.
#[test]
fn the_states_of_the_report_are_refused() {
    let game = played(Config::default(), 3, &[0; 20]);
    let mut v = serde_json::to_value(&game).unwrap();
    v["restaurant"]["queue"][0]["patience"] = Value::from(i32::MAX);
    let bad: Game = serde_json::from_value(v).unwrap();
    let refused = Game::restore(&bad.snapshot()).unwrap_err();
    assert_eq!(refused.to_string(), "inconsistent game state: queue");

    let mut v = serde_json::to_value(&game).unwrap();
    v["restaurant"]["now"] = Value::from((1u32 << 30) + 1);
    let bad: Game = serde_json::from_value(v).unwrap();
    let refused = Game::restore(&bad.snapshot()).unwrap_err();
    assert_eq!(refused.to_string(), "inconsistent game state: clock");
}
