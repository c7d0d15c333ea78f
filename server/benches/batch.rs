#![allow(missing_docs)] // criterion_group! generates undocumented items.

//! The server's cost of one batched Step per environment, without the network: N = 256
//! environments, action masks on (the Python client always asks for them), no expert actions,
//! autoreset NEXT_STEP, uniformly random actions (legal or not), so that episodes end and reset
//! as they do in training. `Throughput::Elements(256)` makes criterion print per-environment
//! rates.
//!
//! - `sim_only`: the simulator's own share: 256 games stepped (and reset when done) plus their
//!   observations and masks, written nowhere: the floor the rest is measured against;
//! - `envs_step`: [`Envs::step`], the simulator and the session layer's [`Batch`];
//! - `envs_step_encode`: that, then the service's conversion to `pb::Batch` and its protobuf
//!   encoding into a reused buffer (as tonic's encoder does);
//! - `decode_step_request`: decoding a `StepRequest` of 256 actions.
//!
//! `cargo bench -p dinerdash-server --bench batch`. Each bench also checks its result.
//!
//! With `DD_BATCH_PROFILE=STEPS` the binary instead runs STEPS Steps of `envs_step_encode` (after
//! the same warm-up) in [`profile_loop`] and exits: a fixed amount of work for a profiler, e.g.
//! `valgrind --tool=callgrind --toggle-collect='*profile_loop*'`, whose instruction count over
//! STEPS x 256 is the per-environment cost, repeatable on a busy machine.

use std::hint::black_box;

use criterion::{Criterion, Throughput, criterion_group};
use dinerdash_server::pb;
use dinerdash_server::service::convert::batch_to;
use dinerdash_server::session::{Autoreset, Envs, ExpertActions, ResetArgs, SessionOptions};
use dinerdash_server::sim::{Config, Game, NUM_ACTIONS, OBSERVATION_SIZE};
use prost::Message;
use rand::{Rng, SeedableRng, rngs::SmallRng};

const N: usize = 256;
/// Distinct action arrays cycled through, so that no two consecutive Steps repeat the actions.
const ACTION_SETS: usize = 64;

/// `ACTION_SETS` arrays of N uniformly random actions, as N little-endian int32 each.
fn random_actions(seed: u64) -> Vec<Vec<u8>> {
    let mut rng = SmallRng::seed_from_u64(seed);
    (0..ACTION_SETS)
        .map(|_| {
            (0..N)
                .flat_map(|_| rng.random_range(0..NUM_ACTIONS as i32).to_le_bytes())
                .collect()
        })
        .collect()
}

/// N environments as the Python client creates them, reset and stepped into play for a while,
/// so that the benchmark starts among episodes of every age.
fn envs(actions: &[Vec<u8>]) -> Envs {
    let options = SessionOptions {
        autoreset: Autoreset::NextStep,
        action_masks: true,
        expert_actions: ExpertActions::None,
    };
    let mut envs = Envs::new(N, Config::default(), options, Some(0)).expect("valid");
    envs.reset(&ResetArgs::default()).expect("reset");
    for a in actions.iter().cycle().take(2000) {
        envs.step(a).expect("step");
    }
    envs
}

fn batch(c: &mut Criterion) {
    let actions = random_actions(1);
    let mut group = c.benchmark_group("batch_n256_masks_next_step");
    group.throughput(Throughput::Elements(N as u64));

    group.bench_function("sim_only", |b| {
        let mut games: Vec<(Game, bool)> = (0..N as u64)
            .map(|i| {
                let mut g = Game::new(Config::default()).expect("valid");
                g.reset(Some(i), None).expect("reset");
                (g, false)
            })
            .collect();
        let mut i = 0;
        b.iter(|| {
            let a = &actions[i % ACTION_SETS];
            i += 1;
            let mut sum = 0i64;
            for ((game, pending), a) in games.iter_mut().zip(a.chunks_exact(4)) {
                if *pending {
                    game.reset(None, None).expect("reset");
                    *pending = false;
                } else {
                    let action = i64::from(i32::from_le_bytes([a[0], a[1], a[2], a[3]]));
                    let o = game.step(action).expect("step");
                    *pending = o.terminated || o.truncated;
                    sum += o.reward;
                }
                let r = game.restaurant();
                sum += i64::from(black_box(r.observation())[0]);
                sum += i64::from(black_box(r.action_mask())[0]);
            }
            sum
        })
    });

    group.bench_function("envs_step", |b| {
        let mut envs = envs(&actions);
        let mut i = 0;
        b.iter(|| {
            let batch = envs.step(&actions[i % ACTION_SETS]).expect("step");
            i += 1;
            assert_eq!(batch.action_masks.len(), N * NUM_ACTIONS);
            batch
        })
    });

    group.bench_function("envs_step_encode", |b| {
        let mut envs = envs(&actions);
        let mut buf = Vec::with_capacity(64 * 1024);
        let mut i = 0;
        b.iter(|| {
            let batch = envs.step(&actions[i % ACTION_SETS]).expect("step");
            i += 1;
            let reply = batch_to(batch);
            buf.clear();
            reply.encode(&mut buf).expect("room to grow");
            assert!(buf.len() > N * (OBSERVATION_SIZE + NUM_ACTIONS));
            buf.len()
        })
    });

    group.bench_function("decode_step_request", |b| {
        let request = pb::StepRequest {
            session_id: "0123456789abcdef0123456789abcdef".into(),
            actions: actions[0].clone(),
        }
        .encode_to_vec();
        b.iter(|| {
            let r = pb::StepRequest::decode(black_box(&request[..])).expect("decodes");
            assert_eq!(r.actions.len(), 4 * N);
            r
        })
    });
    group.finish();
}

/// `steps` Steps of N environments, each converted and encoded as the service does.
#[inline(never)]
fn profile_loop(envs: &mut Envs, actions: &[Vec<u8>], steps: usize) -> usize {
    let mut buf = Vec::with_capacity(64 * 1024);
    let mut bytes = 0;
    for a in actions.iter().cycle().take(steps) {
        let reply = batch_to(envs.step(a).expect("step"));
        buf.clear();
        reply.encode(&mut buf).expect("room to grow");
        bytes += buf.len();
    }
    bytes
}

criterion_group!(benches, batch);

fn main() {
    if let Ok(steps) = std::env::var("DD_BATCH_PROFILE") {
        let steps: usize = steps
            .parse()
            .expect("DD_BATCH_PROFILE is a number of Steps");
        let actions = random_actions(1);
        let mut envs = envs(&actions);
        let bytes = profile_loop(&mut envs, &actions, steps);
        println!("{steps} Steps of {N} environments, {bytes} bytes encoded");
        return;
    }
    benches();
    Criterion::default().configure_from_args().final_summary();
}
