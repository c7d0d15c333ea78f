//! The endpoint's URLs as an axum [`Router`]: which handler answers each path, the GET/HEAD-only
//! rule (POST too under `/api/play`), the headers every response carries, and the token each
//! data route asks for.

use std::collections::HashMap;
use std::sync::Arc;

use axum::Router;
use axum::body::Bytes;
use axum::extract::{DefaultBodyLimit, Path, Query, Request, State};
use axum::http::header::{self, HeaderMap, HeaderValue};
use axum::http::{Method, StatusCode};
use axum::middleware::{self, Next};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post};
use serde::Deserialize;

use super::access::{Refused, Viewer};
use super::feeds::{Feed, NotWatched, Sessions, Watching};
use super::play::{Act, MAX_ACT_BODY, NewGame, PlayError};
use super::{MAX_CONNECTIONS, Site, assets, error, json};
use crate::shutdown::Shutdown;

/// What the handlers serve from.
#[derive(Debug, Clone)]
struct Served {
    /// The sessions, counters and tokens.
    site: Arc<Site>,
    /// Ends the event streams.
    stopping: Shutdown,
}

/// The query of the watch routes.
#[derive(Debug, Deserialize)]
struct EnvParam {
    /// Which environment of the session (default 0).
    env: Option<String>,
}

/// The endpoint's routes over `site`; their event streams end when `stopping` fires.
pub fn router(site: Arc<Site>, stopping: Shutdown) -> Router {
    Router::new()
        .route("/", get(sessions_page))
        .route("/index.html", get(sessions_page))
        .route("/watch/{id}", get(watch_page))
        .route("/static/{name}", get(static_file))
        .route("/metrics", get(metrics))
        .route("/api/sessions", get(sessions_json))
        .route("/api/sessions/events", get(sessions_events))
        .route("/api/watch/{id}", get(watch_json))
        .route("/api/watch/{id}/events", get(watch_events))
        .route("/play", get(play_page))
        .route("/play/{id}", get(play_page))
        .route("/api/play", post(play_start))
        .route("/api/play/{id}", get(play_state))
        .route(
            "/api/play/{id}/act",
            post(play_act).layer(DefaultBodyLimit::max(MAX_ACT_BODY)),
        )
        .route("/api/play/{id}/recording", get(play_recording))
        .fallback(|| async { assets::no_such_page() })
        .with_state(Served { site, stopping })
        .layer(middleware::from_fn(get_or_head))
        .layer(middleware::map_response(guarded))
}

/// What a connection over [`MAX_CONNECTIONS`] gets, whatever it asks: 503.
pub fn busy() -> Router {
    Router::new()
        .fallback(|| async {
            error(
                StatusCode::SERVICE_UNAVAILABLE,
                &format!("this endpoint serves its maximum of {MAX_CONNECTIONS} connections"),
            )
        })
        .layer(middleware::map_response(guarded))
}

/// Only GET and HEAD are served (axum answers HEAD from the GET handler, without the body),
/// and POST under `/api/play` (a new game, an action), where the routes say which.
async fn get_or_head(request: Request, next: Next) -> Response {
    let play = request.uri().path().starts_with("/api/play");
    if matches!(*request.method(), Method::GET | Method::HEAD)
        || (play && *request.method() == Method::POST)
    {
        return next.run(request).await;
    }
    let mut refused = error(
        StatusCode::METHOD_NOT_ALLOWED,
        "only GET and HEAD are served",
    );
    refused
        .headers_mut()
        .insert(header::ALLOW, HeaderValue::from_static("GET, HEAD"));
    refused
}

/// Every response: never cached (the data is live and the URLs hold capabilities), never sent as
/// a referrer, no content sniffing, nothing loaded from elsewhere.
async fn guarded(mut response: Response) -> Response {
    let headers = response.headers_mut();
    let set = [
        (header::CACHE_CONTROL, "no-store"),
        (header::X_CONTENT_TYPE_OPTIONS, "nosniff"),
        (header::REFERRER_POLICY, "no-referrer"),
        (
            header::CONTENT_SECURITY_POLICY,
            "default-src 'self'; img-src 'self' data:",
        ),
    ];
    for (name, value) in set {
        headers.insert(name, HeaderValue::from_static(value));
    }
    response
}

/// Why a data route answers with an error: each mapped to its response once, here.
#[derive(Debug, thiserror::Error)]
enum Refusal {
    /// No valid token: 401, asking for a bearer token.
    #[error(transparent)]
    Token(#[from] Refused),
    /// A watch route that names no environment the viewer may see: 404 or 400.
    #[error(transparent)]
    Watch(#[from] NotWatched),
    /// A play route refused: 404, 400, 409, 429 or 500.
    #[error(transparent)]
    Play(#[from] PlayError),
}

impl IntoResponse for Refusal {
    fn into_response(self) -> Response {
        let message = self.to_string();
        match self {
            Refusal::Token(_) => {
                let mut response = error(StatusCode::UNAUTHORIZED, &message);
                response
                    .headers_mut()
                    .insert(header::WWW_AUTHENTICATE, HeaderValue::from_static("Bearer"));
                response
            }
            Refusal::Watch(NotWatched::NotFound) => error(StatusCode::NOT_FOUND, &message),
            Refusal::Watch(NotWatched::Failed(_)) => {
                error(StatusCode::INTERNAL_SERVER_ERROR, &message)
            }
            Refusal::Watch(_) => error(StatusCode::BAD_REQUEST, &message),
            Refusal::Play(e) => error(
                match e {
                    PlayError::NotFound => StatusCode::NOT_FOUND,
                    PlayError::BadRequest(_) => StatusCode::BAD_REQUEST,
                    PlayError::Conflict(_) => StatusCode::CONFLICT,
                    PlayError::Exhausted(_) => StatusCode::TOO_MANY_REQUESTS,
                    PlayError::Failed(_) => StatusCode::INTERNAL_SERVER_ERROR,
                },
                &message,
            ),
        }
    }
}

/// The viewer whose token `headers` carry.
fn viewer(site: &Site, headers: &HeaderMap) -> Result<Viewer, Refused> {
    let authorization = headers
        .get(header::AUTHORIZATION)
        .map(HeaderValue::as_bytes);
    site.access.viewer(authorization)
}

async fn sessions_page() -> Response {
    assets::page(assets::SESSIONS_PAGE)
}

/// The watch page. It carries no data, and a browser opening it sends no token: on a server with
/// tokens it is served for any ID (the page's feed then answers 404 for an ID that is not the
/// token's), so that the page tells nobody which IDs exist. Without tokens (a local-only
/// endpoint, where every session is the shared identity's) an unknown ID gets the 404 page.
async fn watch_page(State(s): State<Served>, Path(id): Path<String>) -> Response {
    if s.site.access.needs_token() || s.site.store.exists(&Viewer::Anyone.owner(), &id) {
        assets::page(assets::WATCH_PAGE)
    } else {
        assets::not_found(&id)
    }
}

async fn static_file(Path(name): Path<String>) -> Response {
    assets::file(&name)
}

async fn metrics(State(s): State<Served>, headers: HeaderMap) -> Result<Response, Refusal> {
    viewer(&s.site, &headers)?;
    let text = s.site.metrics.render();
    Ok(([(header::CONTENT_TYPE, crate::metrics::CONTENT_TYPE)], text).into_response())
}

async fn sessions_json(State(s): State<Served>, headers: HeaderMap) -> Result<Response, Refusal> {
    let viewer = viewer(&s.site, &headers)?;
    Ok(json(Sessions::new(viewer).snapshot(&s.site)))
}

async fn sessions_events(State(s): State<Served>, headers: HeaderMap) -> Result<Response, Refusal> {
    let viewer = viewer(&s.site, &headers)?;
    Ok(Feed::Sessions(Sessions::new(viewer)).into_sse(s.site, s.stopping))
}

/// The environment a watch route names, attached for the viewer the request's token names. The
/// attach copies the environment under the session's lock, which a planner Step may hold for
/// long: it runs on a blocking thread, not on the async worker (the endpoint's connections are
/// capped, so are these threads).
async fn watching(
    s: &Served,
    headers: &HeaderMap,
    id: String,
    env: EnvParam,
) -> Result<Watching, Refusal> {
    let viewer = viewer(&s.site, headers)?;
    let site = Arc::clone(&s.site);
    let attach = move || Watching::attach(&site, &viewer, &id, env.env.as_deref());
    let attached = tokio::task::spawn_blocking(attach)
        .await
        .map_err(|e| NotWatched::Failed(e.to_string()))?;
    Ok(attached?)
}

async fn watch_json(
    State(s): State<Served>,
    Path(id): Path<String>,
    Query(env): Query<EnvParam>,
    headers: HeaderMap,
) -> Result<Response, Refusal> {
    Ok(json(watching(&s, &headers, id, env).await?.snapshot()))
}

async fn watch_events(
    State(s): State<Served>,
    Path(id): Path<String>,
    Query(env): Query<EnvParam>,
    headers: HeaderMap,
) -> Result<Response, Refusal> {
    let watching = watching(&s, &headers, id, env).await?;
    Ok(Feed::Watch(Box::new(watching)).into_sse(s.site, s.stopping))
}

/// The play page, for a new game (`/play?seed=N&...`) or a game in progress (`/play/{id}`). It
/// carries no data; the game is started and played through `/api/play`, with the token.
async fn play_page() -> Response {
    assets::page(assets::PLAY_PAGE)
}

/// Runs `work` (which may take a session's lock, held long by a planner step) on a blocking
/// thread, as the watch routes' attach does.
async fn blocking<T: Send + 'static>(
    work: impl FnOnce() -> Result<T, PlayError> + Send + 'static,
) -> Result<T, Refusal> {
    let done = tokio::task::spawn_blocking(work)
        .await
        .map_err(|e| PlayError::Failed(e.to_string()))?;
    Ok(done?)
}

async fn play_start(
    State(s): State<Served>,
    Query(params): Query<HashMap<String, String>>,
    headers: HeaderMap,
) -> Result<Response, Refusal> {
    let viewer = viewer(&s.site, &headers)?;
    let new = NewGame::from_query(&params)?;
    let site = Arc::clone(&s.site);
    let state = blocking(move || site.plays.start(&site.store, &viewer, new)).await?;
    Ok(json(state))
}

async fn play_state(
    State(s): State<Served>,
    Path(id): Path<String>,
    headers: HeaderMap,
) -> Result<Response, Refusal> {
    let viewer = viewer(&s.site, &headers)?;
    let site = Arc::clone(&s.site);
    let state = blocking(move || site.plays.state(&site.store, &viewer, &id)).await?;
    Ok(json(state))
}

async fn play_act(
    State(s): State<Served>,
    Path(id): Path<String>,
    headers: HeaderMap,
    body: Bytes,
) -> Result<Response, Refusal> {
    let viewer = viewer(&s.site, &headers)?;
    let act = Act::parse(&body)?;
    let site = Arc::clone(&s.site);
    let state = blocking(move || site.plays.act(&site.store, &viewer, &id, act)).await?;
    Ok(json(state))
}

async fn play_recording(
    State(s): State<Served>,
    Path(id): Path<String>,
    headers: HeaderMap,
) -> Result<Response, Refusal> {
    let viewer = viewer(&s.site, &headers)?;
    // The game's record is locked for the whole of an action (a planner step): not on a worker.
    let site = Arc::clone(&s.site);
    let (text, name) = blocking(move || site.plays.recording(&viewer, &id)).await?;
    let mut response = json(text);
    if let Ok(value) = HeaderValue::from_str(&format!("attachment; filename=\"{name}\"")) {
        response
            .headers_mut()
            .insert(header::CONTENT_DISPOSITION, value);
    }
    Ok(response)
}
