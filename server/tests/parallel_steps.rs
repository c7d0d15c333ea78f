//! A session stepped in chunks on several threads is the session stepped on one: the same
//! Batches (observations, rewards, seeds, expert actions, autoresets, episode ends) and the same
//! environments after every Reset and Step, for every autoreset mode, with and without planner
//! labels; and the store's tally of a parallel session is the serial one's.

use std::sync::Arc;

use dinerdash_server::budget::{Share, Tenant};
use dinerdash_server::cmd::ceiling::Actions;
use dinerdash_server::pools::{SERIAL, StepPool, Stepping, Turn};
use dinerdash_server::session::{
    Autoreset, Batch, Caller, Envs, ExpertActions, Limits, ResetArgs, SessionOptions, Store,
};
use dinerdash_server::sim::Config;

/// Episodes that end within tens of steps: one life, little patience, and a time limit (so
/// both terminations and truncations happen, at different steps in different environments).
fn short_episodes(time_limit: u32) -> Config {
    Config {
        patience: [150, 200],
        decay: [40, 30],
        lives: 1,
        time_limit,
        ..Config::default()
    }
}

/// Three threads (so the chunks do not divide evenly), parallel from two environments.
fn eager_pool() -> StepPool {
    StepPool::new(Stepping {
        threads: 3,
        min_envs: 2,
        min_planner_envs: 2,
    })
}

/// The environments whose episode ended in `batch`.
fn ended(batch: &Batch) -> Vec<bool> {
    batch
        .terminated
        .iter()
        .zip(&batch.truncated)
        .map(|(&t, &u)| t | u != 0)
        .collect()
}

/// Steps a serial and a parallel copy of the same session `steps` times with the same actions
/// (resetting ended environments with a reset mask where autoreset is off, and now and then
/// some others with new seeds), asserting every Batch and the environments equal, and that
/// each environment ended an episode on average.
fn compare(n: usize, expert: ExpertActions, autoreset: Autoreset, steps: usize, config: Config) {
    let options = SessionOptions {
        autoreset,
        action_masks: expert != ExpertActions::None,
        expert_actions: expert,
    };
    let pool = eager_pool();
    assert!(n == 1 || pool.chunks(n, expert == ExpertActions::Planner) > 1);
    let mut serial = Envs::new(n, config, options, Some(7)).unwrap();
    let mut parallel = Envs::new(n, config, options, Some(7)).unwrap();
    let first = ResetArgs::default();
    let a = serial.reset_on(&first, &SERIAL, Turn::default()).unwrap();
    assert_eq!(
        a,
        parallel.reset_on(&first, &pool, Turn::default()).unwrap()
    );
    let what = format!("N={n} {expert:?} {autoreset:?}");
    let mut actions = Actions(n as u64);
    let mut episode_ends = 0;
    for t in 0..steps {
        let a = actions.next(n);
        let one = serial.step_on(&a, &SERIAL, Turn::default()).unwrap();
        let many = parallel.step_on(&a, &pool, Turn::default()).unwrap();
        assert!(one == many, "{what}: step {t} differs");
        let done = ended(&one);
        episode_ends += done.iter().filter(|&&d| d).count();
        // Where nothing resets them, ended episodes are reset by a reset mask; and every so
        // often a few running ones are too, with seeds of their own.
        let mut mask = if autoreset == Autoreset::Disabled {
            done
        } else {
            vec![false; n]
        };
        if t % 17 == 5 {
            mask.iter_mut().step_by(3).for_each(|m| *m = true);
        }
        if mask.contains(&true) {
            let args = ResetArgs {
                seeds: (0..n as u64).map(|i| 1000 * t as u64 + i).collect(),
                reset_mask: mask,
                ..ResetArgs::default()
            };
            let one = serial.reset_on(&args, &SERIAL, Turn::default()).unwrap();
            assert!(
                one == parallel.reset_on(&args, &pool, Turn::default()).unwrap(),
                "{what}: reset after step {t} differs"
            );
        }
    }
    assert_eq!(
        serial.snapshot(),
        parallel.snapshot(),
        "{what}: the environments differ"
    );
    assert!(
        episode_ends >= n,
        "{what}: only {episode_ends} episodes ended"
    );
}

const MODES: [Autoreset; 3] = [
    Autoreset::NextStep,
    Autoreset::SameStep,
    Autoreset::Disabled,
];

#[test]
fn parallel_steps_equal_serial_steps_without_planner_labels() {
    for (n, steps) in [(1, 300), (7, 300), (256, 300), (4096, 150)] {
        for expert in [ExpertActions::None, ExpertActions::Reference] {
            for mode in MODES {
                compare(n, expert, mode, steps, short_episodes(60));
            }
        }
    }
}

#[test]
fn parallel_steps_equal_serial_steps_with_planner_labels() {
    // A planner decision costs ~0.1 ms, so the largest sessions take fewer steps, in episodes
    // cut short enough that each environment still ends at least one.
    for (n, steps, time_limit) in [(1, 300, 120), (7, 300, 120), (256, 40, 15), (4096, 6, 3)] {
        for mode in MODES {
            compare(
                n,
                ExpertActions::Planner,
                mode,
                steps,
                short_episodes(time_limit),
            );
        }
    }
}

#[test]
fn a_parallel_sessions_tally_is_the_serial_ones() {
    let caller = Caller::shared(Arc::new(Tenant::new(
        "parallel-tally".into(),
        Share::default(),
    )));
    let store = |stepping: Stepping| {
        Store::new(
            Limits {
                stepping,
                ..Limits::default()
            },
            Arc::default(),
        )
    };
    let stores = [store(Stepping::SERIAL), store(*eager_pool().stepping())];
    let options = SessionOptions {
        autoreset: Autoreset::SameStep,
        action_masks: true,
        expert_actions: ExpertActions::Reference,
    };
    let sessions: Vec<_> = stores
        .iter()
        .map(|s| {
            let (id, _) = s
                .create(&caller, 300, short_episodes(40), options, Some(3))
                .unwrap();
            s.find(&caller.owner, &id.to_string()).unwrap()
        })
        .collect();
    let mut actions = Actions(1);
    let reset: Vec<Batch> = sessions
        .iter()
        .map(|s| s.reset(&ResetArgs::default()).unwrap())
        .collect();
    assert_eq!(reset[0], reset[1]);
    for _ in 0..100 {
        let a = actions.next(300);
        let one = sessions[0].step(&a).unwrap();
        assert!(one == sessions[1].step(&a).unwrap());
    }
    let tallies: Vec<_> = stores
        .iter()
        .map(|s| s.summaries(&caller.owner, 10).rows.remove(0).tally)
        .collect();
    let (one, many) = (&tallies[0], &tallies[1]);
    assert_eq!(
        (one.steps, one.episodes, one.recent_mean),
        (many.steps, many.episodes, many.recent_mean)
    );
    assert!(one.episodes > 300);
}
