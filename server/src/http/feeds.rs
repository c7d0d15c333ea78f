//! The data behind the pages, as JSON: the sessions a viewer may see with the server's totals
//! ([`Sessions`]), and one watched environment ([`Watching`]); and their server-sent event
//! streams ([`Feed`]).
//!
//! A watch stream looks at its environment's slot at most [`FRAME_INTERVAL`] apart and sends
//! only the latest frame, so a trainer stepping thousands of times a second costs a viewer ~30
//! frames a second; frames in between are dropped. A frame is made only when hyper asks the
//! stream for one, that is once the previous one is written: a viewer that stops reading is
//! dropped after [`super::WRITE_TIMEOUT`], never waited for. The event framing is axum's
//! ([`Sse`]).

use std::collections::HashMap;
use std::convert::Infallible;
use std::sync::Arc;
use std::time::{Duration, Instant};

use axum::response::sse::{Event, KeepAlive, Sse};
use axum::response::{IntoResponse, Response};
use serde::Serialize;

use super::{Site, Viewer};
use crate::policy::expert::expert_action;
use crate::session::watch::{Frame, Summary};
use crate::session::{Autoreset, ExpertActions, SessionError, SessionId};
use crate::shutdown::Shutdown;

/// Shortest time between two frames of a watch stream (~30 a second).
pub const FRAME_INTERVAL: Duration = Duration::from_millis(33);
/// Time between two updates of the sessions stream.
pub const SESSIONS_INTERVAL: Duration = Duration::from_millis(500);
/// Longest silence on a stream: a comment line then tells proxies and the page it is alive.
const KEEPALIVE: Duration = Duration::from_secs(15);
/// Most sessions listed; the most recently used are kept when there are more.
pub const MAX_ROWS: usize = 500;
/// Hex digits of a session ID shown in the table.
const SHORT_ID: usize = 8;

/// An event stream.
pub enum Feed {
    /// The sessions, every [`SESSIONS_INTERVAL`].
    Sessions(Sessions),
    /// One environment, every new frame (at most one per [`FRAME_INTERVAL`]).
    Watch(Box<Watching>),
}

impl Feed {
    /// The feed as a server-sent event stream: events until the environment goes (a `gone`
    /// event) or `shutdown` fires, a comment after [`KEEPALIVE`] of silence. A client that does
    /// not read is dropped by the socket's write deadline ([`super::deadline`]).
    pub fn into_sse(self, site: Arc<Site>, shutdown: Shutdown) -> Response {
        let period = match &self {
            Feed::Sessions(_) => SESSIONS_INTERVAL,
            Feed::Watch(_) => FRAME_INTERVAL,
        };
        let mut ticker = tokio::time::interval(period);
        ticker.set_missed_tick_behavior(tokio::time::MissedTickBehavior::Skip);
        let events = futures_util::stream::unfold(
            Some((self, ticker, shutdown, site)),
            |state| async move {
                let (mut feed, mut ticker, mut shutdown, site) = state?;
                loop {
                    tokio::select! {
                        () = shutdown.wait() => return None,
                        _ = ticker.tick() => {}
                    }
                    let (event, more) = match &mut feed {
                        Feed::Sessions(sessions) => {
                            (Event::default().data(sessions.snapshot(&site)), true)
                        }
                        Feed::Watch(watching) => match watching.viewer.frame() {
                            None => (Event::default().event("gone").data("{}"), false),
                            Some(frame) if frame.seq == watching.sent => continue,
                            Some(frame) => {
                                watching.sent = frame.seq;
                                (Event::default().data(watching.encode(&frame)), true)
                            }
                        },
                    };
                    let next = more.then_some((feed, ticker, shutdown, site));
                    return Some((Ok::<_, Infallible>(event), next));
                }
            },
        );
        Sse::new(events)
            .keep_alive(KeepAlive::new().interval(KEEPALIVE).text("alive"))
            .into_response()
    }
}

/// The sessions a viewer may see; remembers the last counts to give rates.
#[derive(Debug)]
pub struct Sessions {
    /// Who is looking.
    viewer: Viewer,
    /// When the last snapshot was taken, the server's environment steps then, and each listed
    /// session's steps then.
    last: Option<(Instant, u64, HashMap<SessionId, u64>)>,
}

/// One row of the sessions table.
#[derive(Debug, Serialize)]
struct Row {
    id: String,
    short: String,
    tenant: String,
    envs: usize,
    expert: &'static str,
    autoreset: &'static str,
    steps: u64,
    episodes: u64,
    recent_mean: Option<f64>,
    steps_per_s: Option<f64>,
    idle_s: f64,
    viewers: usize,
}

/// The server's totals.
#[derive(Debug, Serialize)]
struct Totals {
    sessions: usize,
    envs: u64,
    env_steps: u64,
    steps_per_s: Option<f64>,
    memory_used: u64,
    memory_budget: u64,
}

#[derive(Debug, Serialize)]
struct SessionsJson {
    sessions: Vec<Row>,
    /// Sessions the viewer may see (more than `sessions` holds when over [`MAX_ROWS`]).
    visible: usize,
    totals: Totals,
    version: &'static str,
}

/// How the page names an expert.
fn expert_name(e: ExpertActions) -> &'static str {
    match e {
        ExpertActions::None => "none",
        ExpertActions::Reference => "reference",
        ExpertActions::Planner => "planner",
    }
}

fn autoreset_name(a: Autoreset) -> &'static str {
    match a {
        Autoreset::NextStep => "next step",
        Autoreset::SameStep => "same step",
        Autoreset::Disabled => "disabled",
    }
}

impl Sessions {
    /// A view for `viewer`.
    pub fn new(viewer: Viewer) -> Sessions {
        Sessions { viewer, last: None }
    }

    /// The sessions and totals now, as JSON; rates are measured since the last snapshot (none
    /// in the first).
    pub fn snapshot(&mut self, site: &Site) -> String {
        let listing = site.store.summaries(&self.viewer.owner(), MAX_ROWS);
        let now = Instant::now();
        let env_steps = site.metrics.env_steps.get();
        let rate = |now_count: u64, then_count: u64, since: Instant| {
            let secs = now.duration_since(since).as_secs_f64();
            (secs > 0.0).then(|| now_count.saturating_sub(then_count) as f64 / secs)
        };
        let rows = listing
            .rows
            .iter()
            .map(|s: &Summary| {
                let id = s.id.to_string();
                let steps_per_s = self.last.as_ref().map(|(then, _, steps)| {
                    let before = steps.get(&s.id).copied().unwrap_or(0);
                    rate(s.tally.steps, before, *then).unwrap_or(0.0)
                });
                Row {
                    short: id[..SHORT_ID].to_owned(),
                    id,
                    tenant: s.tenant.name().to_owned(),
                    envs: s.num_envs,
                    expert: expert_name(s.expert),
                    autoreset: autoreset_name(s.autoreset),
                    steps: s.tally.steps,
                    episodes: s.tally.episodes,
                    recent_mean: s.tally.recent_mean,
                    steps_per_s,
                    idle_s: s.idle_ms as f64 / 1000.0,
                    viewers: s.viewers,
                }
            })
            .collect();
        let totals = Totals {
            sessions: listing.all_sessions,
            envs: listing.all_envs,
            env_steps,
            steps_per_s: self
                .last
                .as_ref()
                .and_then(|(then, before, _)| rate(env_steps, *before, *then)),
            memory_used: site.store.budget().used_bytes(),
            memory_budget: site.store.budget().max_bytes(),
        };
        let steps = listing.rows.iter().map(|s| (s.id, s.tally.steps)).collect();
        self.last = Some((now, env_steps, steps));
        let json = SessionsJson {
            sessions: rows,
            visible: listing.visible,
            totals,
            version: crate::SERVER_VERSION,
        };
        serde_json::to_string(&json).unwrap_or_else(|e| format!("{{\"error\":\"{e}\"}}"))
    }
}

/// Why a watch route attached to no environment.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum NotWatched {
    /// `env` is not a number.
    #[error("env must be a whole number, got {0:?}")]
    Env(String),
    /// No session of this ID that the viewer may see.
    #[error("no such session here: it was closed, it expired, or the ID is wrong")]
    NotFound,
    /// The session has no such environment.
    #[error("{0}")]
    Invalid(String),
    /// The blocking thread that attaches failed (a panic).
    #[error("attaching the viewer failed: {0}")]
    Failed(String),
}

/// A viewer of one environment.
#[derive(Debug)]
pub struct Watching {
    /// The attachment to the environment's slot.
    viewer: crate::session::watch::Viewer,
    /// The session's ID, shortened, for the page's title.
    short: String,
    /// The `seq` of the last frame sent.
    sent: u64,
}

#[derive(Debug, Serialize)]
struct MoveJson {
    tick: u32,
    action: u8,
    reward: i32,
    reset: bool,
}

#[derive(Debug, Serialize)]
struct ExpertJson {
    action: u8,
    /// Which expert: the session's own (`reference`, `planner`), or the reference heuristic
    /// asked for the page (`reference, for this page`).
    by: &'static str,
}

#[derive(Debug, Serialize)]
struct FrameJson<'a> {
    seq: u64,
    session: &'a str,
    env: usize,
    num_envs: usize,
    /// False until the environment's first reset: nothing to draw yet.
    started: bool,
    obs: &'a [i8],
    score: i64,
    lost: u32,
    lives: u32,
    tick: u32,
    terminated: bool,
    truncated: bool,
    /// Newest first.
    moves: Vec<MoveJson>,
    expert: Option<ExpertJson>,
    steps: u64,
    episodes: u64,
    recent_mean: Option<f64>,
}

impl Watching {
    /// Attaches to environment `env` (default 0) of session `id`, if it is `viewer`'s; another
    /// identity's session is not found, as one that does not exist. It may wait for the
    /// session's lock (held by a planner Step): call it on a blocking thread.
    pub fn attach(
        site: &Site,
        viewer: &Viewer,
        id: &str,
        env: Option<&str>,
    ) -> Result<Watching, NotWatched> {
        let env = match env {
            None | Some("") => 0,
            Some(text) => text
                .parse::<usize>()
                .map_err(|_| NotWatched::Env(text.to_owned()))?,
        };
        let attached = site
            .store
            .watch(&viewer.owner(), id, env)
            .map_err(|e| match e {
                SessionError::NotFound(_) => NotWatched::NotFound,
                other => NotWatched::Invalid(other.to_string()),
            })?;
        Ok(Watching {
            viewer: attached,
            short: id.chars().take(SHORT_ID).collect(),
            sent: 0,
        })
    }

    /// The latest frame as JSON.
    pub fn snapshot(&self) -> String {
        match self.viewer.frame() {
            Some(frame) => self.encode(&frame),
            None => serde_json::json!({ "error": "the session is gone" }).to_string(),
        }
    }

    /// `frame` as JSON. Runs without any lock: the frame is a copy.
    fn encode(&self, frame: &Frame) -> String {
        let game = frame.game.as_ref();
        let obs = game.map(|r| r.observation());
        let over = game.is_some_and(|r| r.is_terminated() || r.is_truncated());
        let expert = match (frame.expert, game) {
            (_, None) => None,
            _ if over => None,
            (Some(action), Some(_)) => Some(ExpertJson {
                action,
                by: expert_name(self.viewer.expert()),
            }),
            (None, Some(r)) => Some(ExpertJson {
                action: expert_action(r),
                by: "reference, for this page",
            }),
        };
        let tally = self.viewer.tally();
        let json = FrameJson {
            seq: frame.seq,
            session: &self.short,
            env: self.viewer.env(),
            num_envs: self.viewer.num_envs(),
            started: game.is_some(),
            obs: obs.as_ref().map_or(&[], |o| &o[..]),
            score: game.map_or(0, |r| r.score()),
            lost: game.map_or(0, |r| r.lost()),
            lives: game.map_or(0, |r| r.config().lives),
            tick: game.map_or(0, |r| r.tick()),
            terminated: game.is_some_and(|r| r.is_terminated()),
            truncated: game.is_some_and(|r| r.is_truncated()),
            moves: frame
                .moves()
                .map(|m| MoveJson {
                    tick: m.tick,
                    action: m.action,
                    reward: m.reward,
                    reset: m.reset,
                })
                .collect(),
            expert,
            steps: tally.map_or(0, |t| t.steps),
            episodes: tally.map_or(0, |t| t.episodes),
            recent_mean: tally.and_then(|t| t.recent_mean),
        };
        serde_json::to_string(&json).unwrap_or_else(|e| format!("{{\"error\":\"{e}\"}}"))
    }
}
