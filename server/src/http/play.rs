//! Games a person plays in the browser (`/play`), and their recordings.
//!
//! A game is an ordinary session of one environment in the store, created for the viewer's
//! identity and charged to its share like any other (a tenant's token: that tenant's share; the
//! shared identity: the pages' own small share, [`MAX_RECORDINGS`] sessions). Every action goes
//! through [`FoundSession::step`], the code gRPC's Step runs: there is no second simulator path.
//! A game is therefore on the sessions page and watchable like any session, and expires when
//! idle like any session.
//!
//! Beside the session, [`Plays`] keeps each game's recording: its seed, config and every action
//! in order, the whole game, since the game is deterministic. Each identity keeps its
//! [`MAX_RECORDINGS`] most recent games; a new one past that drops the oldest's recording (and
//! closes its session if still live). Each recording's bytes (at most [`MAX_PLAY_STEPS`]
//! actions) are charged to the memory budget while kept. Another identity's game is not found,
//! exactly as an unknown ID.

use std::collections::HashMap;
use std::sync::{Arc, Mutex, PoisonError};

use serde::{Deserialize, Serialize};

use super::Viewer;
use crate::budget::{Charge, Share, Tenant};
use crate::pb;
use crate::policy::expert_action;
use crate::session::{
    Autoreset, Caller, ExpertActions, FoundSession, Owner, ResetArgs, SessionError, SessionOptions,
    Store,
};
use crate::sim::{self, Config, NUM_ACTIONS, Restaurant};

/// Recordings (games) each identity keeps: the most recent.
pub const MAX_RECORDINGS: usize = 16;
/// Most actions one game records; past them its actions are refused.
pub const MAX_PLAY_STEPS: usize = 100_000;
/// What a recording's bytes are charged as: its actions at most, and the rest.
const RECORDING_BYTES: u64 = MAX_PLAY_STEPS as u64 + 1024;
/// The version string of the recording format.
pub const RECORDING_FORMAT: &str = "dinerdash-play/1";
/// Largest body of an action request (`{"action": 56, "tick": 123456}` is ~30 bytes).
pub const MAX_ACT_BODY: usize = 1024;
/// The session options of a game: one environment, no autoreset (the game ends), the mask for
/// the page's targets, and the planner's choice as one of the two hints.
const OPTIONS: SessionOptions = SessionOptions {
    autoreset: Autoreset::Disabled,
    action_masks: true,
    expert_actions: ExpertActions::Planner,
};

/// Why a play request was refused.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum PlayError {
    /// No game of this ID that the viewer may see.
    #[error("no such game here: the ID is wrong, or the game was dropped for newer ones")]
    NotFound,
    /// A parameter, body or action that is not valid: 400.
    #[error("{0}")]
    BadRequest(String),
    /// An action that cannot be played in the game's state: 409.
    #[error("{0}")]
    Conflict(String),
    /// The server or the identity's share is full: 429.
    #[error("{0}")]
    Exhausted(String),
    /// A state the checks rule out: 500.
    #[error("internal error: {0}")]
    Failed(String),
}

impl From<SessionError> for PlayError {
    fn from(e: SessionError) -> PlayError {
        match e {
            SessionError::NotFound(_) => PlayError::Conflict(
                "this game's session has ended (it was idle for longer than the server keeps \
                 sessions, or was closed); its recording is kept"
                    .into(),
            ),
            SessionError::InvalidArgument(m) => PlayError::BadRequest(m),
            e @ (SessionError::TooManySessions(_) | SessionError::OverBudget(_)) => {
                PlayError::Exhausted(e.to_string())
            }
            e @ (SessionError::EpisodeOver | SessionError::EnvEpisodeOver(_)) => {
                PlayError::Conflict(e.to_string())
            }
            other => PlayError::Failed(other.to_string()),
        }
    }
}

/// A game's configuration as JSON and as the new-game query: the protocol's `GameConfig` (its
/// field names are what the Python client's `config` takes, so that a recording's `config` is
/// one), absent fields the ruleset's ([`pb::GameConfig::config`]).
impl pb::GameConfig {
    /// The field names, for the new-game query.
    const FIELDS: [&'static str; 10] = [
        "arrival_interval",
        "patience_type1",
        "patience_type2",
        "decay_type1",
        "decay_type2",
        "reading_ticks",
        "cooking_ticks",
        "eating_ticks",
        "lives",
        "time_limit",
    ];

    /// Sets field `name` from `value`.
    fn set(&mut self, name: &str, value: &str) -> Result<(), PlayError> {
        let parsed = value.trim().parse::<u32>().map_err(|_| {
            PlayError::BadRequest(format!("{name} must be a whole number, got {value:?}"))
        })?;
        let field = match name {
            "arrival_interval" => &mut self.arrival_interval,
            "patience_type1" => &mut self.patience_type1,
            "patience_type2" => &mut self.patience_type2,
            "decay_type1" => &mut self.decay_type1,
            "decay_type2" => &mut self.decay_type2,
            "reading_ticks" => &mut self.reading_ticks,
            "cooking_ticks" => &mut self.cooking_ticks,
            "eating_ticks" => &mut self.eating_ticks,
            "lives" => &mut self.lives,
            "time_limit" => &mut self.time_limit,
            _ => return Err(PlayError::Failed(format!("no config field {name}"))),
        };
        *field = Some(parsed);
        Ok(())
    }
}

/// What a new game is asked for: a seed (random otherwise) and a configuration.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct NewGame {
    /// The episode's seed.
    pub seed: Option<u64>,
    /// The configuration.
    pub config: Config,
}

impl NewGame {
    /// The new game the query `params` asks for: `seed` and `GameConfig` fields; anything else
    /// is refused, naming what is accepted.
    pub fn from_query(params: &HashMap<String, String>) -> Result<NewGame, PlayError> {
        let mut config = pb::GameConfig::default();
        let mut seed = None;
        for (name, value) in params {
            if name == "seed" {
                if value.trim().is_empty() {
                    continue;
                }
                seed = Some(value.trim().parse::<u64>().map_err(|_| {
                    PlayError::BadRequest(format!(
                        "seed must be a whole number in 0..=2^64-1, got {value:?}"
                    ))
                })?);
            } else if pb::GameConfig::FIELDS.contains(&name.as_str()) {
                config.set(name, value)?;
            } else {
                let shown: String = name.chars().take(32).collect();
                return Err(PlayError::BadRequest(format!(
                    "unknown parameter {shown:?}: a game takes seed and the GameConfig fields {}",
                    pb::GameConfig::FIELDS.join(", ")
                )));
            }
        }
        Ok(NewGame {
            seed,
            config: config.config(),
        })
    }
}

/// An action request's body.
#[derive(Debug, Clone, Copy, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Act {
    /// The action, 0..=56.
    pub action: i64,
    /// The tick the player saw when choosing it: when given and the game has moved on (a
    /// double click, a real-time "wait" that went first), the action is refused.
    pub tick: Option<u64>,
}

impl Act {
    /// The body `bytes` as an action request.
    pub fn parse(bytes: &[u8]) -> Result<Act, PlayError> {
        serde_json::from_slice(bytes).map_err(|e| {
            PlayError::BadRequest(format!(
                "the body must be JSON {{\"action\": 0..=56, \"tick\": N}} (tick optional): {e}"
            ))
        })
    }
}

/// What a game has recorded so far.
#[derive(Debug, Clone, Default)]
struct Record {
    /// Every action, in order.
    actions: Vec<u8>,
    score: i64,
    lost: u32,
    terminated: bool,
    truncated: bool,
    /// The planner's choice in the current state (none once over).
    planner: Option<u8>,
    /// The last action's reward.
    last_reward: Option<i32>,
}

impl Record {
    fn finished(&self) -> bool {
        self.terminated || self.truncated
    }

    /// Takes in a Reset's or Step's batch (one environment).
    fn update(&mut self, batch: &crate::session::Batch) {
        let int = |bytes: &[u8]| i32::from_le_bytes(bytes[..4].try_into().unwrap_or([0; 4]));
        self.score = i64::from(int(&batch.scores));
        self.lost = int(&batch.lost) as u32;
        self.terminated = batch.terminated.first() == Some(&1);
        self.truncated = batch.truncated.first() == Some(&1);
        self.planner = if self.finished() {
            None
        } else {
            batch.expert_actions.first().copied()
        };
    }
}

/// One game: whose, how it began, and its record.
#[derive(Debug)]
struct Game {
    /// The session's ID.
    id: String,
    /// Whose it is.
    owner: Owner,
    seed: u64,
    config: Config,
    /// Locked for the whole of one action, so that the record's order is the steps' order.
    record: Mutex<Record>,
    /// The recording's bytes in the memory budget, given back when it is dropped.
    _charge: Charge,
}

impl Game {
    fn record(&self) -> std::sync::MutexGuard<'_, Record> {
        self.record.lock().unwrap_or_else(PoisonError::into_inner)
    }
}

/// The games of every identity, oldest first.
#[derive(Debug)]
pub struct Plays {
    games: Mutex<Vec<Arc<Game>>>,
    /// The share the shared identity's games count against.
    shared: Arc<Tenant>,
}

impl Default for Plays {
    fn default() -> Self {
        let share = Share {
            max_envs: MAX_RECORDINGS as u64,
            max_sessions: MAX_RECORDINGS as u64,
            max_rollouts: 0,
            ..Share::default()
        };
        Plays {
            games: Mutex::new(Vec::new()),
            shared: Arc::new(Tenant::new("web player".into(), share)),
        }
    }
}

/// The state of a game, as the page draws it.
#[derive(Debug, Serialize)]
struct StateJson<'a> {
    session_id: &'a str,
    seed: u64,
    config: pb::GameConfig,
    ruleset: &'static str,
    obs: Vec<i8>,
    tick: u32,
    score: i64,
    lost: u32,
    lives: u32,
    terminated: bool,
    truncated: bool,
    finished: bool,
    /// 57 flags: which actions are legal now (all false once over).
    mask: Vec<bool>,
    expert: HintsJson,
    /// Actions recorded.
    steps: usize,
    max_steps: usize,
    last_reward: Option<i32>,
    /// The session ended (idle too long, or closed): the game can no longer be played.
    ended: bool,
}

#[derive(Debug, Serialize)]
struct HintsJson {
    /// The reference heuristic's choice.
    reference: Option<u8>,
    /// The look-ahead planner's.
    planner: Option<u8>,
}

/// A recording (format [`RECORDING_FORMAT`]).
#[derive(Debug, Serialize)]
struct RecordingJson<'a> {
    format: &'static str,
    ruleset: &'static str,
    server_version: &'static str,
    session_id: &'a str,
    seed: u64,
    config: pb::GameConfig,
    actions: &'a [u8],
    score: i64,
    steps: usize,
    lost: u32,
    terminated: bool,
    truncated: bool,
    finished: bool,
}

impl Plays {
    fn games(&self) -> std::sync::MutexGuard<'_, Vec<Arc<Game>>> {
        self.games.lock().unwrap_or_else(PoisonError::into_inner)
    }

    /// Game `id` if `owner`'s: another identity's is not found, as an unknown ID.
    fn find(&self, owner: &Owner, id: &str) -> Result<Arc<Game>, PlayError> {
        self.games()
            .iter()
            .find(|g| g.id == id && g.owner.is(owner))
            .cloned()
            .ok_or(PlayError::NotFound)
    }

    /// Starts a game for `viewer`; returns its state as JSON. Takes the session's lock (a
    /// planner step): call it on a blocking thread.
    pub fn start(&self, store: &Store, viewer: &Viewer, new: NewGame) -> Result<String, PlayError> {
        new.config
            .validate()
            .map_err(|e| PlayError::BadRequest(e.to_string()))?;
        let caller = match viewer {
            Viewer::Tenant(tenant) => Caller::tenant(Arc::clone(tenant)),
            Viewer::Anyone | Viewer::SharedToken => Caller::shared(Arc::clone(&self.shared)),
        };
        let seed = match new.seed {
            Some(seed) => seed,
            None => random_seed()?,
        };
        // The identity's oldest games go first, so that the new one fits its share.
        let dropped: Vec<Arc<Game>> = {
            let mut games = self.games();
            let mine = games.iter().filter(|g| g.owner.is(&caller.owner)).count();
            let excess = (mine + 1).saturating_sub(MAX_RECORDINGS);
            let mut dropped = Vec::new();
            games.retain(|g| {
                let drop = dropped.len() < excess && g.owner.is(&caller.owner);
                if drop {
                    dropped.push(Arc::clone(g));
                }
                !drop
            });
            dropped
        };
        for game in dropped {
            // Already ended (expired, closed) is as good.
            let _ = store.close(&game.owner, &game.id);
        }
        let charge = store
            .budget()
            .charge_region(&caller.tenant, RECORDING_BYTES)
            .map_err(|e| PlayError::Exhausted(e.to_string()))?;
        let (id, _) = store.create(&caller, 1, new.config, OPTIONS, None)?;
        let id = id.to_string();
        let started = store.find(&caller.owner, &id).and_then(|found| {
            let args = ResetArgs {
                seed: Some(seed),
                ..ResetArgs::default()
            };
            Ok((found.reset(&args)?, found))
        });
        let (batch, found) = match started {
            Ok(started) => started,
            Err(e) => {
                let _ = store.close(&caller.owner, &id);
                return Err(e.into());
            }
        };
        let mut record = Record::default();
        record.update(&batch);
        let game = Arc::new(Game {
            id,
            owner: caller.owner,
            seed,
            config: new.config,
            record: Mutex::new(record),
            _charge: charge,
        });
        self.games().push(Arc::clone(&game));
        let record = game.record();
        Ok(state(&game, &record, Some(&found)))
    }

    /// Game `id`'s state, if `viewer`'s.
    pub fn state(&self, store: &Store, viewer: &Viewer, id: &str) -> Result<String, PlayError> {
        let game = self.find(&viewer.owner(), id)?;
        let record = game.record();
        let found = store.find(&game.owner, &game.id).ok();
        Ok(state(&game, &record, found.as_ref()))
    }

    /// Plays `act` in game `id`, if `viewer`'s and the action is legal now; returns the new state.
    /// Takes the session's lock: call it on a blocking thread.
    pub fn act(
        &self,
        store: &Store,
        viewer: &Viewer,
        id: &str,
        act: Act,
    ) -> Result<String, PlayError> {
        let game = self.find(&viewer.owner(), id)?;
        let action = u8::try_from(act.action)
            .ok()
            .filter(|&a| usize::from(a) < NUM_ACTIONS)
            .ok_or_else(|| {
                PlayError::BadRequest(format!(
                    "action must be in 0..={}, got {}",
                    NUM_ACTIONS - 1,
                    act.action
                ))
            })?;
        let mut record = game.record();
        if record.finished() {
            return Err(PlayError::Conflict("the game is over".into()));
        }
        let steps = record.actions.len();
        if act.tick.is_some_and(|tick| tick != steps as u64) {
            return Err(PlayError::Conflict(format!(
                "the game is at tick {steps}, not {}: the action was meant for another state",
                act.tick.unwrap_or_default()
            )));
        }
        if steps >= MAX_PLAY_STEPS {
            return Err(PlayError::Conflict(format!(
                "this game has recorded its maximum of {MAX_PLAY_STEPS} actions"
            )));
        }
        let found = store.find(&game.owner, &game.id)?;
        let now = found
            .restaurant(0)
            .ok_or_else(|| PlayError::Failed("the game's environment was never reset".into()))?;
        if now.tick() as usize != steps {
            return Err(PlayError::Conflict(format!(
                "the game's session is at tick {}, its recording at {steps}: something else \
                 stepped it, so the recording can no longer be replayed",
                now.tick()
            )));
        }
        if !now.action_mask()[usize::from(action)] {
            return Err(PlayError::Conflict(format!(
                "action {action} is not legal now (see the mask)"
            )));
        }
        // The actions of a Step, as the wire holds them: little-endian int32.
        let batch = found.step(&i32::from(action).to_le_bytes())?;
        record.actions.push(action);
        record.update(&batch);
        record.last_reward = batch
            .rewards
            .get(..4)
            .and_then(|b| b.try_into().ok())
            .map(i32::from_le_bytes);
        Ok(state(&game, &record, Some(&found)))
    }

    /// Game `id`'s recording as JSON, if `viewer`'s.
    pub fn recording(&self, viewer: &Viewer, id: &str) -> Result<(String, String), PlayError> {
        let game = self.find(&viewer.owner(), id)?;
        let record = game.record();
        let json = RecordingJson {
            format: RECORDING_FORMAT,
            ruleset: sim::RULESET,
            server_version: crate::SERVER_VERSION,
            session_id: &game.id,
            seed: game.seed,
            config: pb::GameConfig::of(&game.config),
            actions: &record.actions,
            score: record.score,
            steps: record.actions.len(),
            lost: record.lost,
            terminated: record.terminated,
            truncated: record.truncated,
            finished: record.finished(),
        };
        let name = format!(
            "dinerdash-play-seed{}-{}.json",
            game.seed,
            &game.id[..8.min(game.id.len())]
        );
        let text = serde_json::to_string(&json).map_err(|e| PlayError::Failed(e.to_string()))?;
        Ok((text, name))
    }
}

/// A random seed below 2^32 (a number every JSON reader holds exactly).
fn random_seed() -> Result<u64, PlayError> {
    use rand::TryRngCore;
    rand::rngs::OsRng
        .try_next_u32()
        .map(u64::from)
        .map_err(|e| PlayError::Failed(format!("no system randomness for a seed: {e}")))
}

/// A game's state as JSON: drawn from its session when it is live (`found`), else from the
/// record alone (an ended session: nothing to draw).
fn state(game: &Game, record: &Record, found: Option<&FoundSession>) -> String {
    let now: Option<Restaurant> = found.and_then(|f| f.restaurant(0));
    let over = record.finished();
    let mask = match (&now, over) {
        (Some(r), false) => r.action_mask().to_vec(),
        _ => vec![false; NUM_ACTIONS],
    };
    let json = StateJson {
        session_id: &game.id,
        seed: game.seed,
        config: pb::GameConfig::of(&game.config),
        ruleset: sim::RULESET,
        obs: now.map(|r| r.observation().to_vec()).unwrap_or_default(),
        tick: now.map_or(record.actions.len() as u32, |r| r.tick()),
        score: record.score,
        lost: record.lost,
        lives: game.config.lives,
        terminated: record.terminated,
        truncated: record.truncated,
        finished: over,
        mask,
        expert: HintsJson {
            reference: now.filter(|_| !over).map(|r| expert_action(&r)),
            planner: record.planner.filter(|_| now.is_some()),
        },
        steps: record.actions.len(),
        max_steps: MAX_PLAY_STEPS,
        last_reward: record.last_reward,
        ended: now.is_none(),
    };
    serde_json::to_string(&json).unwrap_or_else(|e| format!("{{\"error\":\"{e}\"}}"))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::session::Limits;

    fn query(pairs: &[(&str, &str)]) -> HashMap<String, String> {
        pairs
            .iter()
            .map(|(k, v)| ((*k).to_owned(), (*v).to_owned()))
            .collect()
    }

    #[test]
    fn the_query_names_a_seed_and_config_fields_only() {
        let new = NewGame::from_query(&query(&[("seed", "7"), ("lives", "3")])).unwrap();
        assert_eq!(new.seed, Some(7));
        assert_eq!(new.config.lives, 3);
        assert_eq!(new.config.patience, Config::default().patience);
        for bad in [
            query(&[("seed", "-1")]),
            query(&[("lives", "x")]),
            query(&[("speed", "1")]),
        ] {
            assert!(matches!(
                NewGame::from_query(&bad),
                Err(PlayError::BadRequest(_))
            ));
        }
        assert!(Act::parse(b"{\"action\": 3}").is_ok());
        assert!(Act::parse(b"{\"action\": 3, \"x\": 1}").is_err());
        assert!(Act::parse(b"\xff").is_err());
    }

    #[test]
    fn a_game_records_its_actions_and_only_its_owner_sees_it() {
        let store = Store::new(Limits::default(), Arc::default());
        let plays = Plays::default();
        let a = Viewer::Tenant(Arc::new(Tenant::new("a".into(), Share::default())));
        let b = Viewer::Tenant(Arc::new(Tenant::new("b".into(), Share::default())));
        let new = NewGame {
            seed: Some(5),
            config: Config::default(),
        };
        let started: serde_json::Value =
            serde_json::from_str(&plays.start(&store, &a, new).unwrap()).unwrap();
        let id = started["session_id"].as_str().unwrap().to_owned();
        let mask = started["mask"].as_array().unwrap();
        let illegal = mask.iter().position(|m| m == false).unwrap() as i64;
        let act = |viewer: &Viewer, action: i64, tick: Option<u64>| {
            plays.act(&store, viewer, &id, Act { action, tick })
        };
        assert!(matches!(
            act(&a, illegal, None),
            Err(PlayError::Conflict(_))
        ));
        assert!(matches!(act(&a, 57, None), Err(PlayError::BadRequest(_))));
        act(&a, 0, Some(0)).unwrap();
        assert!(matches!(act(&a, 0, Some(0)), Err(PlayError::Conflict(_))));
        act(&a, 0, Some(1)).unwrap();
        assert_eq!(act(&b, 0, None), Err(PlayError::NotFound));
        assert_eq!(plays.recording(&b, &id), Err(PlayError::NotFound));
        assert_eq!(plays.state(&store, &b, &id), Err(PlayError::NotFound));
        let (text, _) = plays.recording(&a, &id).unwrap();
        let recording: serde_json::Value = serde_json::from_str(&text).unwrap();
        assert_eq!(recording["actions"], serde_json::json!([0, 0]));
        assert_eq!(recording["seed"], 5);
        assert_eq!(recording["format"], RECORDING_FORMAT);
        // The same actions through a session of its own give the same score.
        let (twin, _) = store
            .create(
                &Caller::shared(Arc::clone(&plays.shared)),
                1,
                Config::default(),
                OPTIONS,
                None,
            )
            .unwrap();
        let twin = store.find(&Owner::Shared, &twin.to_string()).unwrap();
        twin.reset(&ResetArgs {
            seed: Some(5),
            ..ResetArgs::default()
        })
        .unwrap();
        twin.step(&0i32.to_le_bytes()).unwrap();
        twin.step(&0i32.to_le_bytes()).unwrap();
        let r = twin.restaurant(0).unwrap();
        assert_eq!(recording["score"], r.score());
        assert_eq!(recording["steps"], r.tick());
    }

    #[test]
    fn each_identity_keeps_its_most_recent_games() {
        let store = Store::new(Limits::default(), Arc::default());
        let plays = Plays::default();
        let new = NewGame {
            seed: None,
            config: Config::default(),
        };
        let ids: Vec<String> = (0..MAX_RECORDINGS + 2)
            .map(|_| {
                let json = plays.start(&store, &Viewer::Anyone, new).unwrap();
                let v: serde_json::Value = serde_json::from_str(&json).unwrap();
                v["session_id"].as_str().unwrap().to_owned()
            })
            .collect();
        assert_eq!(plays.games().len(), MAX_RECORDINGS);
        assert_eq!(store.live(), MAX_RECORDINGS);
        for old in &ids[..2] {
            assert_eq!(
                plays.recording(&Viewer::Anyone, old),
                Err(PlayError::NotFound)
            );
        }
        assert!(plays.recording(&Viewer::Anyone, &ids[2]).is_ok());
        // The kept games' sessions and recordings, and nothing of the dropped ones.
        let each = RECORDING_BYTES + crate::session::session_bytes(1);
        assert_eq!(store.budget().used_bytes(), MAX_RECORDINGS as u64 * each);
    }
}
