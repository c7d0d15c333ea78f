//! gRPC round trips, throughput and memory, measured with a Rust tonic client over loopback
//! against the real server binary in its own process (so that its CPU and RSS are its own):
//!
//! - sequential round trips on one connection, each beside its server and client CPU per call:
//!   a loopback TCP ping-pong (the floor: one byte each way between two threads), unary
//!   `ServerInfo`, unary single-environment `Step`, and `StepStream` with one environment;
//! - single-environment Step round trips per second with concurrent clients;
//! - batched environment-steps per second with N = 256, unary and over StepStream;
//! - RSS of the server holding 100,000 idle single-environment sessions (each reset once).
//!
use std::io::{BufRead, BufReader, Read, Write};
use std::net::{TcpListener, TcpStream};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use dinerdash_server::pb::{self, diner_dash_client::DinerDashClient};
use tokio_stream::wrappers::ReceiverStream;
use tonic::transport::Channel;

type Client = DinerDashClient<Channel>;

/// The server binary, stopped (SIGTERM) when dropped.
struct Server {
    child: Child,
    addr: String,
}

impl Server {
    fn start() -> Server {
        let mut child = Command::new(env!("CARGO_BIN_EXE_dinerdash-server"))
            .args([
                "--port",
                "0",
                "--max-sessions",
                "200000",
                "--max-envs-per-session",
                "1024",
            ])
            .env("RUST_LOG", "warn")
            .stdout(Stdio::piped())
            .spawn()
            .expect("start the server binary");
        let mut line = String::new();
        BufReader::new(child.stdout.take().expect("stdout"))
            .read_line(&mut line)
            .expect("read the listening line");
        let addr = line
            .trim()
            .strip_prefix("dinerdash-server listening on ")
            .expect("listening line")
            .to_owned();
        Server { child, addr }
    }

    /// CPU time the server process has used so far (user + system).
    fn cpu(&self) -> Duration {
        cpu_of(&self.child.id().to_string())
    }

    fn rss_kib(&self) -> u64 {
        let status = std::fs::read_to_string(format!("/proc/{}/status", self.child.id()))
            .expect("/proc/<pid>/status");
        status
            .lines()
            .find_map(|l| l.strip_prefix("VmRSS:"))
            .and_then(|v| v.trim().trim_end_matches("kB").trim().parse().ok())
            .expect("VmRSS")
    }
}

/// CPU time process `pid` ("self": this one) has used so far (user + system).
fn cpu_of(pid: &str) -> Duration {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).expect("/proc/<pid>/stat");
    // Fields after the parenthesised command name; utime and stime are the 12th and 13th.
    let rest = stat.rsplit_once(')').map_or("", |(_, r)| r);
    let fields: Vec<&str> = rest.split_whitespace().collect();
    let field = |i: usize| {
        fields
            .get(i)
            .and_then(|f| f.parse::<u64>().ok())
            .unwrap_or(0)
    };
    let ticks = field(11) + field(12);
    // USER_HZ is 100 on Linux.
    Duration::from_millis(ticks * 10)
}

impl Drop for Server {
    fn drop(&mut self) {
        let _ = Command::new("kill")
            .args(["-TERM", &self.child.id().to_string()])
            .status();
        let _ = self.child.wait();
    }
}

async fn connect(addr: &str) -> Client {
    // Large HTTP/2 windows, so that several N = 256 replies in flight are not held back by
    // flow control (gRPC's own clients probe the bandwidth-delay product to the same end).
    let channel = tonic::transport::Endpoint::from_shared(format!("http://{addr}"))
        .expect("address")
        .initial_connection_window_size(16 << 20)
        .initial_stream_window_size(4 << 20)
        .connect()
        .await
        .expect("connect");
    DinerDashClient::new(channel)
}

/// A session of `n` environments, reset, without masks or expert actions.
async fn session(c: &mut Client, n: u32, seed: u64) -> String {
    let id = c
        .create_session(pb::CreateSessionRequest {
            num_envs: n,
            seed: Some(seed),
            // One environment too: episodes that end restart by themselves, as in a vector env.
            autoreset_mode: pb::AutoresetMode::NextStep.into(),
            config: Some(pb::GameConfig {
                // Long episodes: the single-environment loops rarely need a Reset.
                lives: Some(1000),
                ..Default::default()
            }),
            ..Default::default()
        })
        .await
        .expect("create")
        .into_inner()
        .session_id;
    c.reset(pb::ResetRequest {
        session_id: id.clone(),
        ..Default::default()
    })
    .await
    .expect("reset");
    id
}

/// How a loop steps its session.
#[derive(Clone, Copy, PartialEq, Eq)]
enum Via {
    /// One unary Step call per step.
    Unary,
    /// One StepStream for the whole loop, one message each way per step.
    Stream,
}

/// Steps one session for `secs`; returns the environment-steps done.
async fn step_loop(mut c: Client, via: Via, n: u32, seed: u64, secs: Duration) -> u64 {
    let id = session(&mut c, n, seed).await;
    let mut rng = seed.wrapping_mul(0x9e37_79b9_7f4a_7c15) | 1;
    let actions: Vec<Vec<u8>> = (0..64)
        .map(|_| {
            (0..n)
                .flat_map(|_| {
                    rng ^= rng << 13;
                    rng ^= rng >> 7;
                    rng ^= rng << 17;
                    ((rng % 57) as i32).to_le_bytes()
                })
                .collect()
        })
        .collect();
    let (tx, rx) = tokio::sync::mpsc::channel(1);
    let mut replies = match via {
        Via::Unary => None,
        Via::Stream => Some(
            c.step_stream(ReceiverStream::new(rx))
                .await
                .expect("open StepStream")
                .into_inner(),
        ),
    };
    let start = Instant::now();
    let mut calls = 0u64;
    while start.elapsed() < secs {
        let request = pb::StepRequest {
            session_id: id.clone(),
            actions: actions[calls as usize % actions.len()].clone(),
        };
        let batch = match &mut replies {
            None => c.step(request).await.expect("step").into_inner(),
            Some(replies) => {
                tx.send(request).await.expect("send a step");
                replies
                    .message()
                    .await
                    .expect("step")
                    .expect("a reply per request")
            }
        };
        assert_eq!(batch.observations.len(), 40 * n as usize);
        calls += 1;
    }
    drop(tx);
    let _ = c
        .close_session(pb::CloseSessionRequest { session_id: id })
        .await;
    calls * u64::from(n)
}

/// Total environment-steps per second of `clients` concurrent loops (each its own session,
/// sharing `connections` HTTP/2 connections) over `n` environments.
async fn measure(
    addr: &str,
    via: Via,
    clients: usize,
    connections: usize,
    n: u32,
    secs: Duration,
) -> f64 {
    let mut channels = Vec::new();
    for _ in 0..connections {
        channels.push(connect(addr).await);
    }
    let mut tasks = Vec::new();
    for i in 0..clients {
        let c = channels[i % connections].clone();
        tasks.push(tokio::spawn(step_loop(c, via, n, i as u64, secs)));
    }
    let start = Instant::now();
    let mut total = 0;
    for t in tasks {
        total += t.await.expect("client task");
    }
    total as f64 / start.elapsed().as_secs_f64()
}

/// Sequential one-byte ping-pongs over loopback TCP (TCP_NODELAY) between this thread and an
/// echoing thread for `secs`: the floor under any request/reply protocol on this machine.
fn tcp_floor(secs: Duration) -> u64 {
    let listener = TcpListener::bind("127.0.0.1:0").expect("bind");
    let addr = listener.local_addr().expect("address");
    let echo = std::thread::spawn(move || {
        let (mut s, _) = listener.accept().expect("accept");
        s.set_nodelay(true).expect("nodelay");
        let mut byte = [0u8; 1];
        while s.read_exact(&mut byte).is_ok() {
            if s.write_all(&byte).is_err() {
                break;
            }
        }
    });
    let mut s = TcpStream::connect(addr).expect("connect");
    s.set_nodelay(true).expect("nodelay");
    let mut byte = [7u8; 1];
    let start = Instant::now();
    let mut calls = 0;
    while start.elapsed() < secs {
        s.write_all(&byte).expect("ping");
        s.read_exact(&mut byte).expect("pong");
        calls += 1;
    }
    drop(s);
    echo.join().expect("echo thread");
    calls
}

/// Sequential unary ServerInfo calls on one connection for `secs`.
async fn server_info_loop(addr: &str, secs: Duration) -> u64 {
    let mut c = connect(addr).await;
    let start = Instant::now();
    let mut calls = 0;
    while start.elapsed() < secs {
        let info = c.server_info(pb::ServerInfoRequest {}).await.expect("info");
        assert!(!info.get_ref().server_version.is_empty());
        calls += 1;
    }
    calls
}

/// Prints one round-trip line: wall time per call, and the server's and this process's CPU per
/// call, of `calls` made between the two CPU readings.
fn report(what: &str, calls: u64, wall: Duration, server: Duration, client: Duration) {
    let per = |d: Duration| d.as_secs_f64() * 1e6 / calls.max(1) as f64;
    println!(
        "{what:<28} {:>7.1} us/call  {:>7.0} calls/s  server CPU {:>5.1} us/call  client CPU {:>5.1} us/call",
        per(wall),
        calls as f64 / wall.as_secs_f64(),
        per(server),
        per(client)
    );
}

/// The sequential round trips, one line each, side by side.
async fn round_trips(server: &Server, secs: Duration) {
    let (cpu, me, wall) = (server.cpu(), cpu_of("self"), Instant::now());
    let calls = tokio::task::spawn_blocking(move || tcp_floor(secs))
        .await
        .expect("tcp floor");
    // The echo thread is this process's too: "client" is both ends here.
    report(
        "TCP ping-pong (floor)",
        calls,
        wall.elapsed(),
        server.cpu() - cpu,
        cpu_of("self") - me,
    );
    let (cpu, me, wall) = (server.cpu(), cpu_of("self"), Instant::now());
    let calls = server_info_loop(&server.addr, secs).await;
    report(
        "unary ServerInfo",
        calls,
        wall.elapsed(),
        server.cpu() - cpu,
        cpu_of("self") - me,
    );
    for (via, what) in [
        (Via::Unary, "unary Step, 1 env"),
        (Via::Stream, "StepStream, 1 env"),
    ] {
        let c = connect(&server.addr).await;
        let (cpu, me, wall) = (server.cpu(), cpu_of("self"), Instant::now());
        let calls = step_loop(c, via, 1, 1, secs).await;
        // The loop's session create, reset and close are three calls among thousands.
        report(
            what,
            calls,
            wall.elapsed(),
            server.cpu() - cpu,
            cpu_of("self") - me,
        );
    }
}

async fn idle_sessions(server: &Server, count: usize) {
    let before = server.rss_kib();
    let start = Instant::now();
    let clients = 8;
    let mut tasks = Vec::new();
    for k in 0..clients {
        let mut c = connect(&server.addr).await;
        let share = count / clients + usize::from(k < count % clients);
        tasks.push(tokio::spawn(async move {
            for i in 0..share {
                session(&mut c, 1, (k * count + i) as u64).await;
            }
        }));
    }
    for t in tasks {
        t.await.expect("create task");
    }
    let mut c = connect(&server.addr).await;
    let live = c
        .server_info(pb::ServerInfoRequest {})
        .await
        .expect("server info")
        .into_inner()
        .live_sessions;
    let after = server.rss_kib();
    println!(
        "idle sessions: {live} live (created and reset in {:.1} s); server RSS {:.1} MiB before, \
         {:.1} MiB after = {:.0} bytes per session",
        start.elapsed().as_secs_f64(),
        before as f64 / 1024.0,
        after as f64 / 1024.0,
        (after.saturating_sub(before) * 1024) as f64 / live.max(1) as f64
    );
}

fn main() {
    // `cargo bench` passes `--bench`; `cargo test --benches` runs this too: keep that short.
    let quick = !std::env::args().any(|a| a == "--bench");
    let secs = std::env::var("DD_BENCH_SECS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(if quick { 0.2 } else { 3.0 });
    let secs = Duration::from_secs_f64(secs);
    let idle: usize = std::env::var("DD_BENCH_IDLE_SESSIONS")
        .ok()
        .and_then(|s| s.parse().ok())
        .unwrap_or(if quick { 1000 } else { 100_000 });
    let runtime = tokio::runtime::Builder::new_current_thread()
        .enable_all()
        .build()
        .expect("runtime");
    let server = Server::start();
    runtime.block_on(async move {
        round_trips(&server, secs).await;
        if std::env::var_os("DD_BENCH_ROUND_TRIPS_ONLY").is_some() {
            let _ = tokio::task::spawn_blocking(move || drop(server)).await;
            return;
        }
        let runs = [
            (Via::Unary, 1, 1, 1),
            (Via::Unary, 1, 4, 4),
            (Via::Unary, 1, 16, 16),
            (Via::Unary, 1, 16, 2),
            (Via::Unary, 1, 64, 2),
            (Via::Stream, 1, 16, 2),
            (Via::Unary, 256, 1, 1),
            (Via::Stream, 256, 1, 1),
            (Via::Unary, 256, 2, 2),
            (Via::Stream, 256, 2, 2),
            (Via::Unary, 256, 4, 2),
            (Via::Unary, 256, 8, 2),
        ];
        for (via, n, clients, connections) in runs {
            let cpu = server.cpu();
            let wall = Instant::now();
            let rate = measure(&server.addr, via, clients, connections, n, secs).await;
            let share = (server.cpu() - cpu).as_secs_f64() / wall.elapsed().as_secs_f64();
            let what = match (via, n) {
                (Via::Unary, 1) => "single-env Step      ",
                (Via::Stream, 1) => "single-env StepStream",
                (Via::Unary, _) => "N=256 Step           ",
                (Via::Stream, _) => "N=256 StepStream     ",
            };
            let unit = if n == 1 { "steps/s" } else { "env-steps/s" };
            println!(
                "{what} {clients:>2} client(s) on {connections} connection(s): {rate:>10.0} {unit:<11} \
                 (server used {:.2} cores)",
                share
            );
        }
        if idle > 0 {
            idle_sessions(&server, idle).await;
        }
        // Stop the server while this runtime still answers its HTTP/2 goodbye.
        let _ = tokio::task::spawn_blocking(move || drop(server)).await;
    });
}
