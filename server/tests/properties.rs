//! Property tests of the simulator over random action sequences and configurations.

use dinerdash_server::policy::expert_action;
use dinerdash_server::sim::{Config, Game, NUM_ACTIONS, Restaurant};
use proptest::prelude::*;

fn config() -> impl Strategy<Value = Config> {
    (
        1u32..20,
        (1u32..1000, 1u32..1000),
        (0u32..40, 0u32..40),
        (0u32..20, 0u32..20, 0u32..20),
        1u32..8,
        0u32..300,
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

/// Actions biased towards legal ones, so that episodes get somewhere.
fn actions() -> impl Strategy<Value = Vec<(bool, u8)>> {
    prop::collection::vec((any::<bool>(), 0u8..NUM_ACTIONS as u8), 1..400)
}

fn pick(r: &Restaurant, prefer_legal: bool, raw: u8) -> u8 {
    if !prefer_legal {
        return raw;
    }
    let mask = r.action_mask();
    let legal: Vec<u8> = (0..NUM_ACTIONS as u8)
        .filter(|&a| mask[usize::from(a)])
        .collect();
    legal[usize::from(raw) % legal.len()]
}

fn check_invariants(r: &Restaurant) {
    let obs = r.observation();
    assert!(r.queue().len() <= 7);
    let hands = r.hands();
    assert!(hands[0] != 0 || hands[1] == 0, "hands fill in order");
    assert_eq!((obs[38], obs[39]), (hands[0] as i8, hands[1] as i8));
    for t in 1..=6u8 {
        let on_counter = r.counters().contains(&t);
        assert_eq!(
            obs[17 + usize::from(t)],
            i8::from(on_counter),
            "counter of table {t}"
        );
    }
    let (low, high) = dinerdash_server::sim::observation_bounds();
    for i in 0..40 {
        assert!(
            low[i] <= obs[i] && obs[i] <= high[i],
            "obs[{i}] = {} out of bounds",
            obs[i]
        );
    }
    assert!(r.action_mask()[0]);
}

proptest! {
    #![proptest_config(ProptestConfig { cases: 256, ..ProptestConfig::default() })]

    #[test]
    fn random_play_keeps_every_invariant(config in config(), seed in any::<u64>(), plan in actions()) {
        let mut game = Game::new(config).unwrap();
        game.reset(Some(seed), None).unwrap();
        let mut lost = 0;
        for (prefer_legal, raw) in plan {
            let r = *game.restaurant();
            let action = pick(&r, prefer_legal, raw);
            let legal = r.action_mask()[usize::from(action)];
            let out = game.step(i64::from(action)).unwrap();
            let after = game.restaurant();
            check_invariants(after);
            prop_assert!(after.lost() >= lost);
            lost = after.lost();
            prop_assert_eq!(out.reward, after.score() - r.score());
            prop_assert_eq!(out.terminated, after.lost() >= config.lives);
            prop_assert_eq!(after.tick(), r.tick() + 1);
            // A masked-out action changes nothing but time: same state as waiting.
            if !legal {
                let mut waited = r;
                waited.step(0);
                prop_assert_eq!(&waited, after);
            }
            // The expert always proposes an action within range.
            prop_assert!(usize::from(expert_action(after)) < NUM_ACTIONS);
        }
    }

    #[test]
    fn clone_and_snapshot_have_identical_futures(
        seed in any::<u64>(),
        prefix in actions(),
        future in actions(),
    ) {
        let mut game = Game::new(Config::default()).unwrap();
        game.reset(Some(seed), None).unwrap();
        for (prefer_legal, raw) in prefix {
            let a = pick(game.restaurant(), prefer_legal, raw);
            game.step(i64::from(a)).unwrap();
        }
        let mut cloned = game.clone();
        let mut restored = Game::restore(&game.snapshot()).unwrap();
        for (prefer_legal, raw) in &future {
            let a = i64::from(pick(game.restaurant(), *prefer_legal, *raw));
            let want = game.step(a).unwrap();
            prop_assert_eq!(cloned.step(a).unwrap(), want);
            prop_assert_eq!(restored.step(a).unwrap(), want);
        }
        prop_assert_eq!(cloned.restaurant(), game.restaurant());
        prop_assert_eq!(restored.restaurant(), game.restaurant());
        // The random streams continue identically too.
        game.reset(None, None).unwrap();
        cloned.reset(None, None).unwrap();
        restored.reset(None, None).unwrap();
        prop_assert_eq!(cloned.restaurant(), game.restaurant());
        prop_assert_eq!(restored.restaurant(), game.restaurant());
    }

    #[test]
    fn corrupt_snapshots_are_errors_not_panics(seed in any::<u64>(), flips in prop::collection::vec((any::<usize>(), any::<u8>()), 1..8)) {
        let mut game = Game::new(Config::default()).unwrap();
        game.reset(Some(seed), None).unwrap();
        for a in [15, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 0, 1, 7] {
            game.step(a).unwrap();
        }
        let mut bytes = game.snapshot();
        for (at, value) in flips {
            let i = at % bytes.len();
            bytes[i] ^= value;
        }
        if let Ok(mut restored) = Game::restore(&bytes) {
            // Whatever decodes and passes the checks must play without panicking.
            for a in 0..NUM_ACTIONS as i64 {
                restored.step(a).unwrap();
                check_invariants(restored.restaurant());
            }
        }
    }

    #[test]
    fn invalid_configurations_are_typed_errors(patience in 1000u32..5000, lives in 1001u32..) {
        let too_patient = Config { patience: [patience, 800], ..Config::default() };
        prop_assert_eq!(Game::new(too_patient).unwrap_err().field, "patience_type1");
        let too_many_lives = Config { lives, ..Config::default() };
        prop_assert_eq!(Game::new(too_many_lives).unwrap_err().field, "lives");
        prop_assert_eq!(Game::new(Config { lives: 0, ..Config::default() }).unwrap_err().field, "lives");
    }
}

#[test]
fn time_limit_truncates() {
    let mut game = Game::new(Config {
        time_limit: 3,
        ..Config::default()
    })
    .unwrap();
    game.reset(Some(0), None).unwrap();
    let outcomes: Vec<bool> = (0..3).map(|_| game.step(0).unwrap().truncated).collect();
    assert_eq!(outcomes, vec![false, false, true]);
}

#[test]
fn game_state_fits_in_one_kib() {
    assert!(
        std::mem::size_of::<Restaurant>() <= 1024,
        "{}",
        std::mem::size_of::<Restaurant>()
    );
}
