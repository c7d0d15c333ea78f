//! The `ceiling` command: the rates no client of this server can pass, measured on the machine
//! the clients run on, for `python -m dinerdash bench` to print beside them.
//!
//! - **in process**: one session of N environments stepped through the session store, each
//!   Step's Batch built as for a reply, no transport at all (the server's own batch rate);
//! - **Rust gRPC client**: the same over loopback gRPC, a tonic client of a server in this
//!   process, one unary Step after another (what `cargo bench --bench grpc` measures).
//!
//! Both step with uniformly random actions from a fixed stream, as the Python bench does.

use std::sync::Arc;
use std::time::{Duration, Instant};

use crate::budget::{Share, Tenant};
use crate::pb;
use crate::server::{self, Listeners, ServerConfig, ServerError};
use crate::session::{Autoreset, Caller, ExpertActions, Limits, ResetArgs, SessionOptions, Store};
use crate::sim::{Config, NUM_ACTIONS};

/// A fixed stream of random actions, packed as a Step carries them.
struct Actions(u64);

impl Actions {
    fn next(&mut self, n: usize) -> Vec<u8> {
        (0..n)
            .flat_map(|_| {
                self.0 = self
                    .0
                    .wrapping_mul(6364136223846793005)
                    .wrapping_add(1442695040888963407);
                (((self.0 >> 33) % NUM_ACTIONS as u64) as i32).to_le_bytes()
            })
            .collect()
    }
}

/// Env-steps/s of one session of `num_envs` stepped in process for about `time`.
pub fn in_process(num_envs: usize, time: Duration) -> Result<f64, String> {
    let store = Store::new(Limits::default(), Arc::default());
    let caller = Caller::shared(Arc::new(Tenant::new("ceiling".into(), Share::default())));
    let options = SessionOptions {
        autoreset: Autoreset::NextStep,
        action_masks: true,
        expert_actions: ExpertActions::None,
    };
    let n = u32::try_from(num_envs).map_err(|e| e.to_string())?;
    let (id, _) = store
        .create(&caller, n, Config::default(), options, Some(0))
        .map_err(|e| e.to_string())?;
    let session = store
        .find(&caller.owner, &id.to_string())
        .map_err(|e| e.to_string())?;
    session
        .reset(&ResetArgs::default())
        .map_err(|e| e.to_string())?;
    let mut actions = Actions(0);
    let batches: Vec<Vec<u8>> = (0..64).map(|_| actions.next(num_envs)).collect();
    let start = Instant::now();
    let mut steps = 0u64;
    while start.elapsed() < time {
        for a in &batches {
            std::hint::black_box(session.step(a).map_err(|e| e.to_string())?);
        }
        steps += batches.len() as u64;
    }
    Ok(steps as f64 * num_envs as f64 / start.elapsed().as_secs_f64())
}

/// Env-steps/s of one tonic client stepping a session of `num_envs` on a server in this
/// process, over loopback, for about `time`.
pub async fn grpc(num_envs: usize, time: Duration) -> Result<f64, ServerError> {
    let listener = tokio::net::TcpListener::bind("127.0.0.1:0")
        .await
        .map_err(|source| ServerError::Listen {
            addr: "127.0.0.1:0".into(),
            purpose: "",
            source,
        })?;
    let addr = listener.local_addr().map_err(ServerError::LocalAddr)?;
    let (stop, stopped) = tokio::sync::oneshot::channel::<()>();
    let serving = tokio::spawn(server::run(
        Listeners::grpc(listener),
        ServerConfig::default(),
        async {
            let _ = stopped.await;
        },
    ));
    let rate = async {
        let mut client = pb::diner_dash_client::DinerDashClient::connect(format!("http://{addr}"))
            .await
            .map_err(|e| e.to_string())?;
        let created = client
            .create_session(pb::CreateSessionRequest {
                num_envs: u32::try_from(num_envs).map_err(|e| e.to_string())?,
                seed: Some(0),
                autoreset_mode: pb::AutoresetMode::NextStep.into(),
                action_masks: true,
                ..Default::default()
            })
            .await
            .map_err(|e| e.to_string())?
            .into_inner();
        let id = created.session_id;
        client
            .reset(pb::ResetRequest {
                session_id: id.clone(),
                ..Default::default()
            })
            .await
            .map_err(|e| e.to_string())?;
        let mut actions = Actions(0);
        let start = Instant::now();
        let mut steps = 0u64;
        while start.elapsed() < time {
            let request = pb::StepRequest {
                session_id: id.clone(),
                actions: actions.next(num_envs),
            };
            client.step(request).await.map_err(|e| e.to_string())?;
            steps += 1;
        }
        Ok::<f64, String>(steps as f64 * num_envs as f64 / start.elapsed().as_secs_f64())
    }
    .await;
    let _ = stop.send(());
    let _ = serving.await;
    rate.map_err(|e| ServerError::LocalAddr(std::io::Error::other(e)))
}
