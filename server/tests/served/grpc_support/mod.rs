//! Shared by the served tests (`grpc_*` and others): an in-process server on 127.0.0.1:0 that
//! each test stops, a client, packing helpers, and a local model of the Batch a session should
//! return.

#![allow(dead_code)]

use std::net::SocketAddr;
use std::time::Duration;

use dinerdash_server::pb::{self, diner_dash_client::DinerDashClient};
use dinerdash_server::policy::expert_action;
use dinerdash_server::server::{self, Listeners, ServerConfig, ServerError};
use dinerdash_server::sim::{Config, Game};
use tokio::net::TcpListener;
use tokio::sync::oneshot;
use tokio::task::JoinHandle;
use tonic::transport::Channel;

/// Longest a test waits for anything (a stop, an eviction); far above any normal duration.
pub const PATIENCE: Duration = Duration::from_secs(60);

/// A server running inside the test's runtime.
pub struct TestServer {
    /// Where it serves gRPC.
    pub addr: SocketAddr,
    /// Where it serves metrics, when asked for.
    pub metrics_addr: Option<SocketAddr>,
    stop: Option<oneshot::Sender<()>>,
    task: Option<JoinHandle<Result<(), ServerError>>>,
}

impl TestServer {
    /// Starts a server with `config` (its metrics listener is made here when `metrics`).
    pub async fn start_with(config: ServerConfig, metrics: bool) -> TestServer {
        let mut listeners = Listeners::grpc(TcpListener::bind("127.0.0.1:0").await.unwrap());
        let addr = listeners.grpc.local_addr().unwrap();
        let mut metrics_addr = None;
        if metrics {
            let l = TcpListener::bind("127.0.0.1:0").await.unwrap();
            metrics_addr = Some(l.local_addr().unwrap());
            listeners.http = Some(l);
        }
        let (stop, stopped) = oneshot::channel::<()>();
        let task = tokio::spawn(server::run(listeners, config, async {
            let _ = stopped.await;
        }));
        TestServer {
            addr,
            metrics_addr,
            stop: Some(stop),
            task: Some(task),
        }
    }

    /// A server with the default configuration.
    pub async fn start() -> TestServer {
        TestServer::start_with(ServerConfig::default(), false).await
    }

    /// A plain channel to the server (for the health service, or a raw gRPC call).
    pub async fn channel(&self) -> Channel {
        Channel::from_shared(format!("http://{}", self.addr))
            .unwrap()
            .connect()
            .await
            .unwrap()
    }

    /// A plaintext client.
    pub async fn client(&self) -> DinerDashClient<Channel> {
        DinerDashClient::connect(format!("http://{}", self.addr))
            .await
            .unwrap()
            .max_decoding_message_size(64 << 20)
    }

    /// Fires the shutdown future without waiting.
    pub fn trigger_stop(&mut self) {
        if let Some(stop) = self.stop.take() {
            let _ = stop.send(());
        }
    }

    /// Stops the server and checks that it stopped cleanly.
    pub async fn stop(mut self) {
        self.trigger_stop();
        let task = self.task.take().unwrap();
        let result = tokio::time::timeout(PATIENCE, task)
            .await
            .expect("server did not stop")
            .expect("server task panicked");
        result.expect("server returned an error");
    }
}

impl Drop for TestServer {
    fn drop(&mut self) {
        // A failing test still stops its server.
        self.trigger_stop();
    }
}

/// The address a `dinerdash-server` child prints first on stdout (`dinerdash-server listening
/// on ADDR`), read from its piped stdout.
pub fn listening_addr(child: &mut std::process::Child) -> String {
    use std::io::BufRead as _;
    let mut line = String::new();
    std::io::BufReader::new(child.stdout.take().expect("stdout piped"))
        .read_line(&mut line)
        .unwrap();
    line.trim()
        .strip_prefix("dinerdash-server listening on ")
        .unwrap_or_else(|| panic!("unexpected first line {line:?}"))
        .to_owned()
}

/// N actions as little-endian int32.
pub fn pack(actions: &[i32]) -> Vec<u8> {
    actions.iter().flat_map(|a| a.to_le_bytes()).collect()
}

/// Little-endian int32s.
pub fn i32s(bytes: &[u8]) -> Vec<i32> {
    bytes
        .chunks_exact(4)
        .map(|c| i32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect()
}

/// Little-endian uint32s.
pub fn u32s(bytes: &[u8]) -> Vec<u32> {
    bytes
        .chunks_exact(4)
        .map(|c| u32::from_le_bytes([c[0], c[1], c[2], c[3]]))
        .collect()
}

/// A CreateSession request.
pub fn create_request(
    num_envs: u32,
    mode: pb::AutoresetMode,
    seed: Option<u64>,
) -> pb::CreateSessionRequest {
    pb::CreateSessionRequest {
        num_envs,
        config: None,
        seed,
        autoreset_mode: mode.into(),
        action_masks: true,
        expert_actions: true,
        ..pb::CreateSessionRequest::default()
    }
}

/// Creates a session and returns its ID.
pub async fn create(
    client: &mut DinerDashClient<Channel>,
    request: pb::CreateSessionRequest,
) -> String {
    client
        .create_session(request)
        .await
        .unwrap()
        .into_inner()
        .session_id
}

/// Steps a session.
pub async fn step(client: &mut DinerDashClient<Channel>, id: &str, actions: &[i32]) -> pb::Batch {
    client
        .step(pb::StepRequest {
            session_id: id.to_owned(),
            actions: pack(actions),
        })
        .await
        .unwrap()
        .into_inner()
}

/// Snapshots a session: the bytes that Restore turns back into it.
pub async fn snapshot(client: &mut DinerDashClient<Channel>, id: &str) -> Vec<u8> {
    client
        .snapshot(pb::SnapshotRequest {
            session_id: id.to_owned(),
            ..Default::default()
        })
        .await
        .unwrap()
        .into_inner()
        .snapshot
}

/// Restores a snapshot into a new session; returns its id.
pub async fn restore(client: &mut DinerDashClient<Channel>, snapshot: Vec<u8>) -> String {
    client
        .restore(pb::RestoreRequest { snapshot })
        .await
        .unwrap()
        .into_inner()
        .session_id
}

/// Resets a session with `seed`.
pub async fn reset(
    client: &mut DinerDashClient<Channel>,
    id: &str,
    seed: Option<u64>,
) -> pb::Batch {
    client
        .reset(pb::ResetRequest {
            session_id: id.to_owned(),
            seed,
            ..Default::default()
        })
        .await
        .unwrap()
        .into_inner()
}

/// A deterministic stream of actions in 0..=56 (no randomness in tests).
pub struct Actions(u64);

impl Actions {
    /// A stream fixed by `seed`.
    pub fn new(seed: u64) -> Actions {
        Actions(
            seed.wrapping_mul(6364136223846793005)
                .wrapping_add(1442695040888963407),
        )
    }

    /// The next action.
    pub fn next(&mut self) -> i32 {
        self.0 = self
            .0
            .wrapping_mul(6364136223846793005)
            .wrapping_add(1442695040888963407);
        ((self.0 >> 33) % 57) as i32
    }
}

/// The session modes a [`Model`] follows.
#[derive(Clone, Copy, PartialEq, Eq, Debug)]
pub enum Mode {
    NextStep,
    SameStep,
    Disabled,
}

/// What a session of N environments should answer, computed with local games: the oracle the
/// gRPC answers are compared with, written from the proto's comments.
pub struct Model {
    pub games: Vec<Game>,
    pending: Vec<bool>,
    mode: Mode,
}

impl Model {
    /// N games reset with `seed + i`.
    pub fn reset(n: usize, config: Config, seed: u64, mode: Mode) -> (Model, pb::Batch) {
        let mut games = vec![Game::new(config).unwrap(); n];
        let mut b = empty_batch(n);
        for (i, g) in games.iter_mut().enumerate() {
            let info = g.reset(Some(seed.wrapping_add(i as u64)), None).unwrap();
            push_row(
                &mut b,
                0,
                false,
                false,
                Some((info.seed, info.stream_episodes)),
                g,
            );
        }
        let model = Model {
            games,
            pending: vec![false; n],
            mode,
        };
        (model, b)
    }

    /// The Batch a Step with `actions` should return.
    pub fn step(&mut self, actions: &[i32]) -> pb::Batch {
        let n = self.games.len();
        let mut b = empty_batch(n);
        for ((g, pending), &action) in self.games.iter_mut().zip(&mut self.pending).zip(actions) {
            if *pending {
                let info = g.reset(None, None).unwrap();
                *pending = false;
                push_row(
                    &mut b,
                    0,
                    false,
                    false,
                    Some((info.seed, info.stream_episodes)),
                    g,
                );
                continue;
            }
            let out = g.step(i64::from(action)).unwrap();
            let ended = out.terminated || out.truncated;
            let mut reset = None;
            if self.mode == Mode::SameStep {
                let r = g.restaurant();
                let (obs, score, lost, tick, mask, expert) = if ended {
                    let (r_obs, r_mask) = (r.observation(), r.action_mask());
                    (
                        r_obs,
                        r.score() as i32,
                        r.lost(),
                        r.tick(),
                        r_mask,
                        expert_action(r),
                    )
                } else {
                    ([0; 40], 0, 0, 0, [false; 57], 0)
                };
                b.final_observations.extend(obs.iter().map(|&v| v as u8));
                b.final_scores.extend(score.to_le_bytes());
                b.final_lost.extend(lost.to_le_bytes());
                b.final_ticks.extend(tick.to_le_bytes());
                b.final_action_masks
                    .extend(mask.iter().map(|&m| u8::from(m)));
                b.final_expert_actions.push(expert);
                if ended {
                    let info = g.reset(None, None).unwrap();
                    reset = Some((info.seed, info.stream_episodes));
                }
            }
            if self.mode == Mode::NextStep && ended {
                *pending = true;
            }
            push_row(
                &mut b,
                out.reward as i32,
                out.terminated,
                out.truncated,
                reset,
                g,
            );
        }
        b
    }
}

fn empty_batch(n: usize) -> pb::Batch {
    pb::Batch {
        num_envs: n as u32,
        ..Default::default()
    }
}

/// A game's observation as the wire carries it: 40 int8 as bytes.
pub fn wire_observation(g: &Game) -> Vec<u8> {
    g.restaurant()
        .observation()
        .iter()
        .map(|&v| v as u8)
        .collect()
}

fn push_row(
    b: &mut pb::Batch,
    reward: i32,
    terminated: bool,
    truncated: bool,
    reset: Option<(u64, u32)>,
    g: &Game,
) {
    let r = g.restaurant();
    b.observations.extend(wire_observation(g));
    b.rewards.extend(reward.to_le_bytes());
    b.terminated.push(u8::from(terminated));
    b.truncated.push(u8::from(truncated));
    b.scores.extend((r.score() as i32).to_le_bytes());
    b.lost.extend(r.lost().to_le_bytes());
    b.ticks.extend(r.tick().to_le_bytes());
    b.action_masks
        .extend(r.action_mask().iter().map(|&m| u8::from(m)));
    b.expert_actions.push(expert_action(r));
    b.reset.push(u8::from(reset.is_some()));
    b.seeds.push(reset.map_or(0, |r| r.0));
    b.stream_episodes.push(reset.map_or(0, |r| r.1));
}

/// A channel to `url` over TLS that trusts `cert_pem` for the name `localhost`.
pub async fn tls_channel(url: String, cert_pem: &str) -> Channel {
    use tonic::transport::{Certificate, ClientTlsConfig};
    Channel::from_shared(url)
        .unwrap()
        .tls_config(
            ClientTlsConfig::new()
                .ca_certificate(Certificate::from_pem(cert_pem))
                .domain_name("localhost"),
        )
        .unwrap()
        .connect()
        .await
        .unwrap()
}

/// Sends `request` (an HTTP/1.1 request as it is) to `addr` and reads the reply until the server
/// closes: the whole text, with its status.
pub async fn http_exchange(addr: SocketAddr, request: &str) -> (u16, String) {
    use tokio::io::{AsyncReadExt, AsyncWriteExt};
    let mut stream = tokio::net::TcpStream::connect(addr).await.unwrap();
    stream.write_all(request.as_bytes()).await.unwrap();
    let mut text = String::new();
    tokio::time::timeout(PATIENCE, stream.read_to_string(&mut text))
        .await
        .unwrap()
        .unwrap();
    let status = text.get(9..12).and_then(|s| s.parse().ok());
    (
        status.unwrap_or_else(|| panic!("not an HTTP reply: {text}")),
        text,
    )
}

/// Reads the metrics endpoint with a plain HTTP/1.1 GET.
pub async fn scrape(addr: SocketAddr) -> String {
    let (status, text) =
        http_exchange(addr, "GET /metrics HTTP/1.1\r\nHost: localhost\r\n\r\n").await;
    assert_eq!(status, 200, "{text}");
    text
}

/// The value of metric line `name` (with labels, if any) in a scrape.
pub fn metric(text: &str, name: &str) -> u64 {
    text.lines()
        .find_map(|l| l.strip_prefix(name).and_then(|rest| rest.strip_prefix(' ')))
        .unwrap_or_else(|| panic!("no metric {name} in\n{text}"))
        .trim()
        .parse()
        .unwrap()
}
