#![allow(missing_docs)] // criterion_group! generates undocumented items.
//! What watching costs a trainer: the latency of one Step (the session store's, as the service
//! calls it) with nobody watching, and with 20 viewers attached over HTTP that never read their
//! event streams (stalled browsers), all on one environment or each on its own.
//!
//! The HTTP endpoint runs in this process on 127.0.0.1:0, as in the server; the viewers are raw
//! TCP connections that send their request and then read nothing.

use std::hint::black_box;
use std::sync::Arc;
use std::time::Duration;

use criterion::{Criterion, criterion_group, criterion_main};
use dinerdash_server::budget::{Share, Tenant};
use dinerdash_server::http::{self, Access, Site};
use dinerdash_server::metrics::Metrics;
use dinerdash_server::session::{
    Autoreset, Caller, ExpertActions, Limits, Owner, ResetArgs, SessionOptions, Store,
};
use dinerdash_server::shutdown;
use dinerdash_server::sim::Config;
use tokio::io::AsyncWriteExt;
use tokio::net::{TcpSocket, TcpStream};

/// Viewers attached in the watched cases.
const VIEWERS: usize = 20;

/// A session of `n` environments, reset, stepped by waiting.
fn session(store: &Store, n: u32) -> String {
    let caller = Caller::shared(Arc::new(Tenant::new("bench".into(), Share::default())));
    let options = SessionOptions {
        autoreset: Autoreset::NextStep,
        action_masks: false,
        expert_actions: ExpertActions::None,
    };
    let (id, _) = store
        .create(&caller, n, Config::default(), options, Some(7))
        .unwrap();
    let id = id.to_string();
    store
        .reset(&Owner::Shared, &id, &ResetArgs::default())
        .unwrap();
    id
}

/// A viewer of environment `env` that never reads: a small receive buffer, so that its stream
/// backs up quickly.
async fn stalled_viewer(addr: std::net::SocketAddr, id: &str, env: usize) -> TcpStream {
    let socket = TcpSocket::new_v4().unwrap();
    socket.set_recv_buffer_size(4096).unwrap();
    let mut stream = socket.connect(addr).await.unwrap();
    let request = format!("GET /api/watch/{id}/events?env={env} HTTP/1.1\r\nHost: bench\r\n\r\n");
    stream.write_all(request.as_bytes()).await.unwrap();
    stream
}

/// Waits until session `id` has `n` viewers.
fn wait_for_viewers(store: &Store, id: &str, n: usize) {
    for _ in 0..2000 {
        let listing = store.summaries(&Owner::Shared, usize::MAX);
        if listing
            .rows
            .iter()
            .any(|r| r.id.to_string() == id && r.viewers == n)
        {
            return;
        }
        std::thread::sleep(Duration::from_millis(5));
    }
    panic!("the viewers did not attach");
}

fn viewers_of(store: &Store, id: &str) -> usize {
    let listing = store.summaries(&Owner::Shared, usize::MAX);
    listing
        .rows
        .iter()
        .find(|r| r.id.to_string() == id)
        .map_or(0, |r| r.viewers)
}

fn bench_watch(c: &mut Criterion) {
    let rt = tokio::runtime::Builder::new_multi_thread()
        .worker_threads(2)
        .enable_all()
        .build()
        .unwrap();
    let metrics = Arc::new(Metrics::default());
    let store = Store::new(Limits::default(), Arc::clone(&metrics));
    let (trigger, stopping) = shutdown::channel();
    let listener = rt
        .block_on(tokio::net::TcpListener::bind("127.0.0.1:0"))
        .unwrap();
    let addr = listener.local_addr().unwrap();
    let site = Arc::new(Site::new(store.clone(), metrics, Access::default()));
    let server = rt.spawn(http::serve(listener, site, stopping));

    let mut group = c.benchmark_group("step_with_viewers");
    group.measurement_time(Duration::from_secs(4));
    group.warm_up_time(Duration::from_secs(1));
    for (n, spread) in [(1usize, false), (VIEWERS, true)] {
        let id = session(&store, n as u32);
        let actions = vec![0u8; 4 * n];
        let label = if spread {
            format!("{n} envs")
        } else {
            format!("{n} env")
        };
        group.bench_function(format!("{label}, no viewer"), |b| {
            b.iter(|| black_box(store.step(&Owner::Shared, &id, &actions).unwrap()))
        });
        let viewers: Vec<TcpStream> = rt.block_on(async {
            let mut v = Vec::new();
            for k in 0..VIEWERS {
                v.push(stalled_viewer(addr, &id, if spread { k } else { 0 }).await);
            }
            v
        });
        wait_for_viewers(&store, &id, VIEWERS);
        let on = if spread { "one per env" } else { "on env 0" };
        group.bench_function(format!("{label}, {VIEWERS} stalled viewers {on}"), |b| {
            b.iter(|| black_box(store.step(&Owner::Shared, &id, &actions).unwrap()))
        });
        eprintln!(
            "{label}: {} of {VIEWERS} stalled viewers still attached after the measurement",
            viewers_of(&store, &id)
        );
        drop(viewers);
    }
    group.finish();
    trigger.fire();
    rt.block_on(server).unwrap();
}

criterion_group!(benches, bench_watch);
criterion_main!(benches);
