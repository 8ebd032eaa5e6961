//! The HTTP API under `/v1` (axum). Every refusal is a 4xx with a JSON `{"error": ...}` body.

use std::sync::{Arc, Mutex, OnceLock};
use std::time::{Duration, Instant};

use axum::body::Bytes;
use axum::extract::{DefaultBodyLimit, MatchedPath, Path, RawQuery, Request, State};
use axum::http::{header, HeaderMap, StatusCode};
use axum::middleware::{self, Next};
use axum::response::sse::{Event, KeepAlive, Sse};
use axum::response::{IntoResponse, Response};
use axum::routing::{get, post, put};
use axum::{Json, Router};
use furnace_proto::{
    decode_chunk, is_hash, ApiError, FailureReport, Heartbeat, HeartbeatReply, JobSpec, LeaseRequest,
    Priority, Ready, Stored, Submitted, MAX_LEASE_WAIT_MS,
};
use metrics_exporter_prometheus::{Matcher, PrometheusBuilder, PrometheusHandle};
use serde::Deserialize;
use tokio::sync::Notify;

use crate::state::{CoordError, Coordinator};
use crate::store::Store;

/// Shared state of the server.
#[derive(Clone)]
pub struct AppState {
    pub coord: Arc<Mutex<Coordinator>>,
    /// The coordinator's store: files and bundles are read and written through it, without the
    /// coordinator's lock.
    store: Arc<dyn Store>,
    /// Bearer token required on every request, when set.
    pub token: Option<String>,
    /// Wakes lease requests held open for work: signalled when work may have appeared.
    work: Arc<Notify>,
    /// Submissions whose scenes load at once; the others wait their turn.
    loads: Arc<tokio::sync::Semaphore>,
    /// Set when the server shuts down: open event streams end.
    closing: Arc<tokio::sync::watch::Sender<bool>>,
    /// Connections served at once ([`MAX_CONNECTIONS`] unless set).
    max_connections: usize,
    /// Time a client has to send a request's headers ([`HEADER_READ_TIMEOUT`] unless set).
    pub header_timeout: Duration,
    /// Time a request may take, its body included ([`REQUEST_TIMEOUT`] unless set); an event
    /// stream's response streams on after it.
    pub request_timeout: Duration,
    /// Bytes of request bodies being received at once, all requests together
    /// ([`BODY_BUDGET`] unless set, with [`AppState::with_body_budget`]). A request waits for
    /// its share (its declared length) before its body is read: at most half the request time
    /// limit, then it is answered 503 with `Retry-After`.
    body_budget: Arc<tokio::sync::Semaphore>,
    /// The budget's size, in bytes.
    budget_bytes: usize,
    /// The largest body accepted: [`MAX_BODY`], or the budget if smaller.
    max_body: usize,
    /// The largest file upload accepted ([`MAX_FILE`] unless set): it streams to disk.
    max_file: u64,
    /// Event streams open at once (a quarter of the connection cap unless set): each holds
    /// a connection for as long as its job runs.
    event_streams: Arc<tokio::sync::Semaphore>,
    /// Stored files no job uses are removed once this old ([`UNUSED_FILES`] unless set);
    /// checked at start and every hour.
    pub unused_files: Duration,
}

/// Request bodies received at once, in bytes, by default.
pub const BODY_BUDGET: usize = 1 << 30;
/// The budget's unit: permits are KiB.
const BUDGET_UNIT: usize = 1024;

/// How long a stored file no job uses is kept: a client uploads a bundle's files, then submits.
pub const UNUSED_FILES: Duration = Duration::from_secs(24 * 3600);
/// The least of it: a submission under way touches its files, and must find them after.
pub const UNUSED_FILES_AT_LEAST: Duration = Duration::from_secs(3600);

/// Scenes loaded at once (each may take a core and much memory while it loads).
pub const CONCURRENT_LOADS: usize = 2;
/// The longest idempotency key, in bytes.
pub const MAX_IDEMPOTENCY_KEY: usize = 200;

impl AppState {
    /// Also installs the process's Prometheus recorder, once: metrics are recorded from here on.
    pub fn new(coord: Arc<Mutex<Coordinator>>, token: Option<String>) -> AppState {
        prometheus();
        let store = coord.lock().unwrap_or_else(|e| e.into_inner()).store();
        AppState {
            coord,
            store,
            token,
            work: Arc::new(Notify::new()),
            loads: Arc::new(tokio::sync::Semaphore::new(CONCURRENT_LOADS)),
            closing: Arc::new(tokio::sync::watch::channel(false).0),
            max_connections: MAX_CONNECTIONS,
            header_timeout: HEADER_READ_TIMEOUT,
            request_timeout: REQUEST_TIMEOUT,
            unused_files: UNUSED_FILES,
            body_budget: Arc::new(tokio::sync::Semaphore::new(BODY_BUDGET / BUDGET_UNIT)),
            max_body: MAX_BODY,
            max_file: MAX_FILE,
            budget_bytes: BODY_BUDGET,
            event_streams: Arc::new(tokio::sync::Semaphore::new(MAX_CONNECTIONS / 4)),
        }
    }

    /// Sets the in-flight budget for request bodies (bytes, at least 64 KiB); no body may be
    /// larger than the budget or [`MAX_BODY`].
    pub fn with_body_budget(mut self, bytes: usize) -> AppState {
        let bytes = bytes.clamp(64 * BUDGET_UNIT, u32::MAX as usize * BUDGET_UNIT);
        self.body_budget = Arc::new(tokio::sync::Semaphore::new(bytes / BUDGET_UNIT));
        self.max_body = MAX_BODY.min(bytes);
        self.budget_bytes = bytes;
        self
    }

    /// Sets the largest file upload accepted, in bytes.
    pub fn with_max_file(mut self, bytes: u64) -> AppState {
        self.max_file = bytes;
        self
    }

    /// Sets the connection cap, and with it the number of event streams open at once (a
    /// quarter of it): streams alone cannot take every connection from the workers.
    pub fn with_max_connections(mut self, n: usize) -> AppState {
        self.max_connections = n.max(1);
        self.event_streams = Arc::new(tokio::sync::Semaphore::new((n / 4).max(1)));
        self
    }

    /// Tells waiting lease requests to look again.
    fn new_work(&self) {
        self.work.notify_waiters();
    }

    fn lock(&self) -> std::sync::MutexGuard<'_, Coordinator> {
        self.coord.lock().unwrap_or_else(|e| e.into_inner())
    }
}

fn error(status: StatusCode, msg: impl Into<String>) -> Response {
    (status, Json(ApiError { error: msg.into() })).into_response()
}

impl IntoResponse for CoordError {
    fn into_response(self) -> Response {
        let status = match &self {
            CoordError::Invalid(_) => StatusCode::BAD_REQUEST,
            CoordError::Unknown(_) => StatusCode::NOT_FOUND,
            CoordError::Refused(_) => StatusCode::CONFLICT,
            CoordError::Unrenderable(_) => StatusCode::UNPROCESSABLE_ENTITY,
            CoordError::TooLarge(_) => StatusCode::PAYLOAD_TOO_LARGE,
            CoordError::Busy(_) => StatusCode::SERVICE_UNAVAILABLE,
            CoordError::Internal(_) => StatusCode::INTERNAL_SERVER_ERROR,
        };
        if status == StatusCode::SERVICE_UNAVAILABLE {
            let mut r = error(status, self.to_string());
            r.headers_mut().insert(header::RETRY_AFTER, header::HeaderValue::from_static("1"));
            return r;
        }
        if status.is_server_error() {
            // The details (paths on this host among them) go to the log, not to the client.
            tracing::error!("{self}");
            return error(status, "internal error (the coordinator's log has the details)");
        }
        error(status, self.to_string())
    }
}

/// Refusals made by the framework (a body over the limit, a path parameter of the wrong
/// type) as JSON errors like every other.
async fn json_errors(resp: Response) -> Response {
    let json = resp
        .headers()
        .get(header::CONTENT_TYPE)
        .is_some_and(|v| v.as_bytes().starts_with(b"application/json"));
    if !resp.status().is_client_error() || json {
        return resp;
    }
    let status = resp.status();
    let body = axum::body::to_bytes(resp.into_body(), 4096).await.unwrap_or_default();
    error(status, String::from_utf8_lossy(&body).trim())
}

type ApiResult = Result<Response, CoordError>;

/// Runs slow work (files, scenes, decoding) on the blocking pool, off the async threads.
async fn blocking<T: Send + 'static>(f: impl FnOnce() -> T + Send + 'static) -> Result<T, CoordError> {
    tokio::task::spawn_blocking(f).await.map_err(|e| CoordError::Internal(e.to_string()))
}

fn json_body<T: for<'de> Deserialize<'de>>(body: &Bytes, what: &str) -> Result<T, CoordError> {
    serde_json::from_slice(body).map_err(|e| {
        // serde quotes the offending value: a huge one is cut, not echoed whole.
        let mut e = e.to_string();
        if e.len() > 512 {
            let mut end = 512;
            while !e.is_char_boundary(end) {
                end -= 1;
            }
            e.truncate(end);
            e.push_str(" [cut]");
        }
        CoordError::Invalid(format!("{what}: invalid JSON: {e}"))
    })
}

/// Largest request body held in memory: scene files and partials.
pub const MAX_BODY: usize = 256 << 20;

/// Largest file upload (`PUT /v1/files/{hash}` streams to disk, so it is not bounded by
/// [`MAX_BODY`] nor held in the in-memory budget beyond [`STREAM_HOLD`]).
pub const MAX_FILE: u64 = 64 << 30;

/// What a streaming file upload holds of the in-memory body budget while it runs: about
/// what its queue of chunks can hold.
const STREAM_HOLD: usize = 8 << 20;

/// The OpenAPI 3 description of every route below, served at `/v1/openapi.json`.
pub const OPENAPI: &str = include_str!("openapi.json");

/// Every (method, path) the router serves, in OpenAPI path syntax (`{action}` spelled out).
/// A test holds this list, the OpenAPI document and the live router to each other.
pub const ROUTES: &[(&str, &str)] = &[
    ("get", "/"),
    ("get", "/healthz"),
    ("get", "/readyz"),
    ("get", "/metrics"),
    ("get", "/v1/stats"),
    ("get", "/v1/workers"),
    ("get", "/v1/openapi.json"),
    ("put", "/v1/files/{hash}"),
    ("get", "/v1/files/{hash}"),
    ("head", "/v1/files/{hash}"),
    ("get", "/v1/bundles/{hash}"),
    ("post", "/v1/jobs"),
    ("get", "/v1/jobs"),
    ("get", "/v1/jobs/{id}"),
    ("delete", "/v1/jobs/{id}"),
    ("get", "/v1/jobs/{id}/events"),
    ("get", "/v1/jobs/{id}/preview.png"),
    ("get", "/v1/jobs/{id}/result.exr"),
    ("get", "/v1/jobs/{id}/frames/{frame}/preview.png"),
    ("get", "/v1/jobs/{id}/frames/{frame}/result.exr"),
    ("post", "/v1/jobs/{id}/cancel"),
    ("post", "/v1/jobs/{id}/pause"),
    ("post", "/v1/jobs/{id}/resume"),
    ("post", "/v1/jobs/{id}/priority"),
    ("post", "/v1/leases"),
    ("post", "/v1/jobs/{id}/chunks/{chunk}/heartbeat"),
    ("post", "/v1/jobs/{id}/chunks/{chunk}/fail"),
    ("put", "/v1/jobs/{id}/chunks/{chunk}/result"),
];

pub fn router(state: AppState) -> Router {
    // Probes, metrics and the dashboard's page answer without the token (orchestrators and
    // Prometheus call them bare; the page asks for the token and sends it with its requests).
    let open = Router::new()
        .route("/", get(|| async { ([(header::CONTENT_TYPE, "text/html; charset=utf-8")], DASHBOARD) }))
        .route("/healthz", get(|| async { "ok" }))
        .route("/readyz", get(readyz))
        .route("/metrics", get(metrics_text))
        .with_state(state.clone());
    Router::new()
        .route("/v1/openapi.json", get(|| async { ([(header::CONTENT_TYPE, "application/json")], OPENAPI) }))
        .route("/v1/files/{hash}", put(put_file).get(get_file).head(head_file))
        .route("/v1/bundles/{hash}", get(get_bundle))
        .route(
            "/v1/stats",
            get(|State(s): State<AppState>| async move { Json(s.lock().stats(Instant::now())) }),
        )
        .route(
            "/v1/workers",
            get(|State(s): State<AppState>| async move { Json(s.lock().workers(Instant::now())) }),
        )
        .route("/v1/jobs", post(post_job).get(list_jobs))
        .route("/v1/jobs/{id}", get(get_job).delete(delete_job))
        .route("/v1/jobs/{id}/events", get(job_events))
        .route("/v1/jobs/{id}/preview.png", get(preview))
        .route("/v1/jobs/{id}/result.exr", get(result))
        .route("/v1/jobs/{id}/frames/{frame}/preview.png", get(frame_preview))
        .route("/v1/jobs/{id}/frames/{frame}/result.exr", get(frame_result))
        .route("/v1/jobs/{id}/priority", post(priority))
        .route("/v1/jobs/{id}/{action}", post(control))
        .route("/v1/leases", post(lease))
        .route("/v1/jobs/{id}/chunks/{chunk}/heartbeat", post(heartbeat))
        .route("/v1/jobs/{id}/chunks/{chunk}/fail", post(fail))
        .route("/v1/jobs/{id}/chunks/{chunk}/result", put(upload))
        .fallback(|| async { error(StatusCode::NOT_FOUND, "no such endpoint (see /v1)") })
        .layer(middleware::from_fn_with_state(state.clone(), body_budget))
        .layer(middleware::from_fn_with_state(state.clone(), auth))
        .layer(middleware::from_fn_with_state(state.clone(), time_limit))
        .layer(DefaultBodyLimit::max(state.max_body))
        .layer(middleware::map_response(json_errors))
        .with_state(state)
        .merge(open)
        .layer(middleware::from_fn(timed))
}

/// The dashboard: one page of HTML and JavaScript, no build step.
pub const DASHBOARD: &str = include_str!("dashboard.html");

/// Buckets of every `*_seconds` histogram: 1 ms to 10 minutes.
const SECONDS_BUCKETS: [f64; 14] =
    [0.001, 0.0025, 0.01, 0.025, 0.1, 0.25, 1.0, 2.5, 10.0, 30.0, 60.0, 120.0, 300.0, 600.0];

/// The process's Prometheus recorder, installed on first use; `None` when another recorder was
/// installed first.
fn prometheus() -> Option<&'static PrometheusHandle> {
    static HANDLE: OnceLock<Option<PrometheusHandle>> = OnceLock::new();
    HANDLE
        .get_or_init(|| {
            let builder = PrometheusBuilder::new()
                .set_buckets_for_metric(Matcher::Suffix("_seconds".into()), &SECONDS_BUCKETS)
                .ok()?;
            match builder.install_recorder() {
                Ok(h) => {
                    describe_metrics();
                    Some(h)
                }
                Err(e) => {
                    tracing::warn!("no /metrics: {e}");
                    None
                }
            }
        })
        .as_ref()
}

/// Counters and histograms without labels: (name, unit, help). Described once, and registered
/// at zero at start, so that rates and alerts see every series before its first event.
const SERIES: &[(&str, Option<metrics::Unit>, &str)] = {
    use metrics::Unit::{Bytes, Seconds};
    &[
        ("furnace_samples_rendered_total", None, "Samples merged into jobs"),
        ("furnace_chunk_failures_total", None, "Chunks workers reported they could not render"),
        ("furnace_lease_expirations_total", None, "Leases that expired without an upload"),
        ("furnace_duplicate_uploads_total", None, "Uploads refused because their chunk was merged"),
        ("furnace_upload_bytes_total", Some(Bytes), "Bytes of partials uploaded (compressed)"),
        ("furnace_merged_bytes_total", Some(Bytes), "Bytes of accumulation merged (decoded)"),
        ("furnace_checkpoint_bytes_total", Some(Bytes), "Bytes of checkpoints written"),
        ("furnace_chunk_duration_seconds", Some(Seconds), "Lease to merge, per chunk"),
        ("furnace_upload_duration_seconds", Some(Seconds), "Upload handling: decode, store, merge"),
        ("furnace_merge_duration_seconds", Some(Seconds), "Merging one partial into its job"),
        ("furnace_checkpoint_duration_seconds", Some(Seconds), "Writing one checkpoint"),
    ]
};

fn describe_metrics() {
    use metrics::{describe_counter, describe_gauge, describe_histogram, Unit};
    describe_gauge!("furnace_jobs", "Jobs by state");
    describe_gauge!("furnace_chunks", "Chunks of the coordinator's jobs by state");
    describe_gauge!("furnace_pending_chunks", "Pending chunks of queued and running jobs (work to hand out)");
    describe_gauge!("furnace_workers", "Workers by state: busy, idle, lost");
    describe_counter!("furnace_chunk_retries_total", "Chunks handed out again, by reason (failed, expired)");
    for reason in ["failed", "expired"] {
        metrics::counter!("furnace_chunk_retries_total", "reason" => reason).increment(0);
    }
    describe_histogram!(
        "furnace_http_request_duration_seconds",
        Unit::Seconds,
        "HTTP requests by method, route and status"
    );
    for &(name, unit, help) in SERIES {
        if name.ends_with("_seconds") {
            match unit {
                Some(u) => describe_histogram!(name, u, help),
                None => describe_histogram!(name, help),
            }
            let _ = metrics::histogram!(name);
        } else {
            match unit {
                Some(u) => describe_counter!(name, u, help),
                None => describe_counter!(name, help),
            }
            metrics::counter!(name).increment(0);
        }
    }
}

/// Records every request's duration under its route's pattern (not its path: job ids would
/// make a series per job). Held lease requests count their wait.
async fn timed(req: Request, next: Next) -> Response {
    let route = req.extensions().get::<MatchedPath>().map(|m| m.as_str().to_string());
    let method = req.method().as_str().to_string();
    let t = Instant::now();
    let resp = next.run(req).await;
    let route = route.unwrap_or_else(|| "unmatched".into());
    let status = resp.status().as_u16().to_string();
    metrics::histogram!("furnace_http_request_duration_seconds", "method" => method, "route" => route, "status" => status)
        .record(t.elapsed().as_secs_f64());
    resp
}

/// `/metrics`: the counters and histograms recorded so far, and the farm's gauges as of now.
async fn metrics_text(State(s): State<AppState>) -> Response {
    let Some(handle) = prometheus() else {
        return error(StatusCode::SERVICE_UNAVAILABLE, "metrics are not recorded in this process");
    };
    let stats = s.lock().stats(Instant::now());
    for (state, n) in &stats.jobs {
        metrics::gauge!("furnace_jobs", "state" => state.clone()).set(*n as f64);
    }
    for (state, n) in &stats.chunks {
        metrics::gauge!("furnace_chunks", "state" => state.clone()).set(*n as f64);
    }
    for (state, n) in &stats.workers {
        metrics::gauge!("furnace_workers", "state" => state.clone()).set(*n as f64);
    }
    metrics::gauge!("furnace_pending_chunks").set(stats.pending_chunks as f64);
    ([(header::CONTENT_TYPE, "text/plain; version=0.0.4")], handle.render()).into_response()
}

/// Ready when the coordinator's state answers: its lock is free within a second.
async fn readyz(State(s): State<AppState>) -> Response {
    let coord = s.coord.clone();
    let probe = tokio::task::spawn_blocking(move || coord.lock().map(|c| c.job_ids().len()).unwrap_or(0));
    match tokio::time::timeout(Duration::from_secs(1), probe).await {
        Ok(Ok(jobs)) => Json(Ready { ready: true, jobs: jobs as u64 }).into_response(),
        _ => error(StatusCode::SERVICE_UNAVAILABLE, "the coordinator's state is busy"),
    }
}

/// When a request's time is up (it has been answered 408 by then).
#[derive(Clone, Copy)]
struct Deadline(Instant);

/// A request (body included) that takes longer than the limit is answered 408: a client
/// trickling its body cannot hold a connection slot.
async fn time_limit(State(s): State<AppState>, mut req: Request, next: Next) -> Response {
    // A file upload also gets the time its declared length takes at MIN_UPLOAD_RATE.
    let upload = is_file_upload(&req)
        .then(|| {
            req.headers()
                .get(header::CONTENT_LENGTH)
                .and_then(|v| v.to_str().ok())
                .and_then(|v| v.parse::<u64>().ok())
        })
        .flatten()
        .map_or(Duration::ZERO, |len| Duration::from_secs_f64(len.min(s.max_file) as f64 / MIN_UPLOAD_RATE));
    let limit = s.request_timeout + upload;
    req.extensions_mut().insert(Deadline(Instant::now() + limit));
    match tokio::time::timeout(limit, next.run(req)).await {
        Ok(r) => r,
        Err(_) => error(StatusCode::REQUEST_TIMEOUT, format!("the request took longer than {limit:?}")),
    }
}

/// Whether `req` uploads a file (`PUT /v1/files/{hash}`), which streams to disk.
fn is_file_upload(req: &Request) -> bool {
    req.method() == axum::http::Method::PUT && req.uri().path().starts_with("/v1/files/")
}

/// Bytes a second a file upload must keep up on average: on top of the request time limit,
/// an upload gets the time its length takes at this rate.
const MIN_UPLOAD_RATE: f64 = 8.0 * 1024.0 * 1024.0;

async fn auth(State(s): State<AppState>, req: Request, next: Next) -> Response {
    if let Some(token) = &s.token {
        let ok = req
            .headers()
            .get(header::AUTHORIZATION)
            .and_then(|v| v.to_str().ok())
            .and_then(|v| v.split_once(' '))
            // The scheme is case-insensitive (RFC 9110 11.1); hashes compare in constant time.
            .is_some_and(|(scheme, t)| {
                scheme.eq_ignore_ascii_case("bearer")
                    && blake3::hash(t.as_bytes()) == blake3::hash(token.as_bytes())
            });
        if !ok {
            return error(StatusCode::UNAUTHORIZED, "missing or wrong token (Authorization: Bearer ...)");
        }
    }
    next.run(req).await
}

/// Holds a request until its body fits in the in-flight budget (its declared length; a body
/// without a length is refused: 411); refuses one larger than the limit. A request with
/// neither a length nor a chunked body has none.
async fn body_budget(State(s): State<AppState>, req: Request, next: Next) -> Response {
    if req.headers().contains_key(header::TRANSFER_ENCODING) {
        // A chunked body's size is known only at its end: held at the largest allowed, a few
        // slow ones would take the whole budget.
        return error(StatusCode::LENGTH_REQUIRED, "a request body needs a Content-Length");
    }
    let declared = req
        .headers()
        .get(header::CONTENT_LENGTH)
        .and_then(|v| v.to_str().ok())
        .and_then(|v| v.parse::<u64>().ok());
    let len = declared.unwrap_or(0);
    // A file upload streams to disk: its own limit, and only its queue held in the budget.
    let streamed = is_file_upload(&req);
    let limit = if streamed { s.max_file } else { s.max_body as u64 };
    if len > limit {
        return CoordError::TooLarge(format!("the body ({len} bytes) is over the limit of {limit} bytes"))
            .into_response();
    }
    let held = if streamed { len.min(STREAM_HOLD as u64).min(s.budget_bytes as u64) } else { len };
    let units = (held as usize).div_ceil(BUDGET_UNIT) as u32;
    if units == 0 {
        return next.run(req).await;
    }
    let wait = s.request_timeout / 2;
    let permit = match tokio::time::timeout(wait, s.body_budget.clone().acquire_many_owned(units)).await {
        Ok(Ok(p)) => p,
        _ => {
            metrics::counter!("furnace_requests_over_budget_total").increment(1);
            return CoordError::Busy(format!(
                "the coordinator is receiving its limit of {} bytes of requests at once (--body-budget-mb); try again",
                s.budget_bytes
            ))
            .into_response();
        }
    };
    let resp = next.run(req).await;
    drop(permit);
    resp
}

/// A request body as a blocking reader, fed by the server's task: a file upload streams to
/// disk on a blocking thread, never whole in memory.
struct BodyReader {
    rx: tokio::sync::mpsc::Receiver<Bytes>,
    cur: Bytes,
}

impl std::io::Read for BodyReader {
    fn read(&mut self, out: &mut [u8]) -> std::io::Result<usize> {
        while self.cur.is_empty() {
            match self.rx.blocking_recv() {
                Some(b) => self.cur = b,
                // The feeder stopped: at the end of the body, or on an error it reports itself.
                None => return Ok(0),
            }
        }
        let n = out.len().min(self.cur.len());
        out[..n].copy_from_slice(&self.cur.split_to(n));
        Ok(n)
    }
}

async fn put_file(State(s): State<AppState>, Path(hash): Path<String>, body: axum::body::Body) -> ApiResult {
    if !is_hash(&hash) {
        return Err(CoordError::Invalid(format!("'{hash}' is not a BLAKE3 hex hash")));
    }
    let store = s.store.clone();
    let (tx, rx) = tokio::sync::mpsc::channel::<Bytes>(8);
    let writer = tokio::task::spawn_blocking(move || {
        store.put_file_from(&hash, &mut BodyReader { rx, cur: Bytes::new() })
    });
    // Fed chunk by chunk; a body that breaks off or runs over the limit is not stored (the
    // writer sees its end early, and the hash check refuses what it got).
    let mut stream = body.into_data_stream();
    let mut got = 0usize;
    let mut failed = None;
    while let Some(chunk) = futures_util::StreamExt::next(&mut stream).await {
        let chunk = match chunk {
            Ok(c) => c,
            Err(e) => {
                failed = Some(CoordError::Invalid(format!("the body broke off: {e}")));
                break;
            }
        };
        got += chunk.len();
        if got as u64 > s.max_file {
            failed =
                Some(CoordError::TooLarge(format!("the body is over the limit of {} bytes", s.max_file)));
            break;
        }
        if tx.send(chunk).await.is_err() {
            break; // the writer is done: a good copy was stored already, or it failed
        }
    }
    drop(tx);
    if let Some(e) = failed {
        // The writer, fed a part, refuses it; its result does not matter.
        writer.await.ok();
        return Err(e);
    }
    let stored = writer.await.map_err(|e| CoordError::Internal(e.to_string()))??;
    let code = if stored { StatusCode::CREATED } else { StatusCode::OK };
    Ok((code, Json(Stored { stored })).into_response())
}

async fn head_file(State(s): State<AppState>, Path(hash): Path<String>) -> StatusCode {
    if is_hash(&hash) && s.store.has_file(&hash) {
        // Asked for before a submission: kept from garbage collection for a while longer.
        s.store.touch_file(&hash);
        StatusCode::OK
    } else {
        StatusCode::NOT_FOUND
    }
}

async fn get_file(State(s): State<AppState>, Path(hash): Path<String>) -> ApiResult {
    if !is_hash(&hash) {
        return Err(CoordError::Invalid(format!("'{hash}' is not a BLAKE3 hex hash")));
    }
    let store = s.store.clone();
    let file = blocking(move || store.open_file(&hash).ok_or(hash))
        .await?
        .map_err(|hash| CoordError::Unknown(format!("no file {hash}")))?;
    // Streamed from disk, 64 KiB at a time: a download never holds the file in memory.
    let len = file.metadata().map(|m| m.len()).ok();
    let chunks = futures_util::stream::unfold(Some(tokio::fs::File::from_std(file)), |f| async move {
        use tokio::io::AsyncReadExt;
        let mut f = f?;
        let mut buf = vec![0u8; 64 << 10];
        match f.read(&mut buf).await {
            Ok(0) => None,
            Ok(n) => {
                buf.truncate(n);
                Some((Ok(Bytes::from(buf)), Some(f)))
            }
            Err(e) => Some((Err(e), None)),
        }
    });
    let mut resp = axum::body::Body::from_stream(chunks).into_response();
    if let Some(n) = len {
        resp.headers_mut().insert(header::CONTENT_LENGTH, n.into());
    }
    Ok(resp)
}

async fn get_bundle(State(s): State<AppState>, Path(hash): Path<String>) -> ApiResult {
    if !is_hash(&hash) {
        return Err(CoordError::Invalid(format!("'{hash}' is not a bundle hash")));
    }
    let store = s.store.clone();
    let bytes = blocking(move || store.bundle_manifest(&hash).ok_or(hash))
        .await?
        .map_err(|hash| CoordError::Unknown(format!("no bundle {hash}")))?;
    Ok(([(header::CONTENT_TYPE, "application/json")], bytes).into_response())
}

async fn post_job(
    State(s): State<AppState>,
    axum::Extension(started): axum::Extension<Deadline>,
    headers: HeaderMap,
    body: Bytes,
) -> ApiResult {
    let spec: JobSpec = json_body(&body, "job spec")?;
    let key = match headers.get("idempotency-key") {
        None => None,
        Some(v) => {
            let k = v.to_str().ok().filter(|k| !k.is_empty() && k.len() <= MAX_IDEMPOTENCY_KEY);
            let e = || format!("an Idempotency-Key has 1 to {MAX_IDEMPOTENCY_KEY} visible ASCII characters");
            Some(k.ok_or_else(|| CoordError::Invalid(e()))?.to_string())
        }
    };
    let coord = s.coord.clone();
    // The client is answered 408 when the request's time is up; a load still running then
    // submits nothing when it ends (no job appears after its client was told it failed).
    let deadline = started.0;
    // The turn goes with the load: a client that hangs up does not free it early.
    let turn = s.loads.clone().acquire_owned().await.map_err(|e| CoordError::Internal(e.to_string()))?;
    let (id, created) = blocking(move || {
        let _turn = turn;
        crate::state::submit(&coord, spec, key.as_deref(), Some(deadline))
    })
    .await??;
    s.new_work();
    let status = if created { StatusCode::CREATED } else { StatusCode::OK };
    Ok((status, Json(Submitted { id })).into_response())
}

/// Most jobs one `GET /v1/jobs` lists, and how many unless asked.
pub const MAX_LIST: usize = 10_000;
const LIST: usize = 1000;

/// Jobs in order of id, a page at a time: `?limit=` (1000 unless given, at most 10000) after
/// `?after=ID`; the next page starts after the last id of this one.
async fn list_jobs(State(s): State<AppState>, RawQuery(q): RawQuery) -> ApiResult {
    let (mut limit, mut after) = (LIST, None);
    for kv in q.as_deref().unwrap_or("").split('&').filter(|kv| !kv.is_empty()) {
        match kv.split_once('=') {
            Some(("limit", v)) => {
                limit = v
                    .parse()
                    .ok()
                    .filter(|n| (1..=MAX_LIST).contains(n))
                    .ok_or_else(|| CoordError::Invalid(format!("limit must be 1 to {MAX_LIST}")))?
            }
            Some(("after", v)) => after = Some(v.to_string()),
            _ => return Err(CoordError::Invalid("GET /v1/jobs takes ?limit= and ?after= only".into()).into()),
        }
    }
    let c = s.lock();
    let page: Result<Vec<_>, _> =
        c.job_ids_after(after.as_deref(), limit).iter().map(|id| c.status(id)).collect();
    Ok(Json(page?).into_response())
}

async fn get_job(State(s): State<AppState>, Path(id): Path<String>) -> ApiResult {
    Ok(Json(s.lock().status(&id)?).into_response())
}

async fn job_events(State(s): State<AppState>, Path(id): Path<String>) -> ApiResult {
    s.lock().status(&id)?;
    // Held by the stream until it ends.
    let turn = s.event_streams.clone().try_acquire_owned().map_err(|_| {
        CoordError::Busy("too many event streams are open; poll GET /v1/jobs/{id} instead".into())
    })?;
    // Ends when the job does, or when the server shuts down.
    let closing = s.closing.subscribe();
    let stream = futures_util::stream::unfold(
        (s, id, closing, false, turn),
        |(s, id, mut closing, finished, turn)| async move {
            if finished || *closing.borrow() {
                return None;
            }
            let status = s.lock().status(&id).ok()?;
            let done =
                matches!(status.state, furnace_proto::JobState::Done | furnace_proto::JobState::Cancelled);
            let event = Event::default().event("progress").json_data(&status).ok()?;
            if !done {
                tokio::select! {
                    _ = tokio::time::sleep(Duration::from_millis(500)) => {}
                    _ = closing.changed() => {}
                }
            }
            Some((Ok::<_, std::convert::Infallible>(event), (s, id, closing, done, turn)))
        },
    );
    Ok(Sse::new(stream).keep_alive(KeepAlive::default()).into_response())
}

async fn delete_job(State(s): State<AppState>, Path(id): Path<String>) -> ApiResult {
    let coord = s.coord.clone();
    blocking(move || crate::state::delete(&coord, &id)).await??;
    Ok(StatusCode::NO_CONTENT.into_response())
}

/// A frame of a frame-range job: its own job's id.
fn frame_job(s: &AppState, id: &str, frame: &str) -> Result<String, CoordError> {
    let n = frame.parse().map_err(|_| CoordError::Invalid(format!("'{frame}' is not a frame number")))?;
    s.lock().frame_job(id, n)
}

async fn frame_preview(State(s): State<AppState>, Path((id, frame)): Path<(String, String)>) -> ApiResult {
    let job = frame_job(&s, &id, &frame)?;
    preview(State(s), Path(job)).await
}

async fn frame_result(State(s): State<AppState>, Path((id, frame)): Path<(String, String)>) -> ApiResult {
    let job = frame_job(&s, &id, &frame)?;
    result(State(s), Path(job)).await
}

async fn preview(State(s): State<AppState>, Path(id): Path<String>) -> ApiResult {
    let picture = s.lock().picture(&id)?;
    // A finished job's result is read without the lock.
    let img = blocking(move || picture.image()).await??;
    let bytes = img.png_bytes(0.0).map_err(|e| CoordError::Internal(format!("preview: {e}")))?;
    Ok(([(header::CONTENT_TYPE, "image/png")], bytes).into_response())
}

async fn result(State(s): State<AppState>, Path(id): Path<String>) -> ApiResult {
    let path = s.lock().result_path(&id)?;
    let bytes = blocking(move || std::fs::read(path)).await??;
    Ok(([(header::CONTENT_TYPE, "image/x-exr")], bytes).into_response())
}

async fn control(State(s): State<AppState>, Path((id, action)): Path<(String, String)>) -> ApiResult {
    let coord = s.coord.clone();
    let status = blocking(move || crate::state::control(&coord, &id, &action)).await??;
    s.new_work();
    Ok(Json(status).into_response())
}

async fn priority(State(s): State<AppState>, Path(id): Path<String>, body: Bytes) -> ApiResult {
    let p: Priority = json_body(&body, "priority")?;
    let coord = s.coord.clone();
    let status = blocking(move || crate::state::set_priority(&coord, &id, p.priority)).await??;
    s.new_work();
    Ok(Json(status).into_response())
}

async fn lease(State(s): State<AppState>, body: Bytes) -> ApiResult {
    let req: LeaseRequest = json_body(&body, "lease request")?;
    if req.worker.is_empty() || req.worker.len() > 200 {
        return Err(CoordError::Invalid("worker name must be 1 to 200 bytes".into()));
    }
    // A long poll ends well inside the request time limit.
    let wait = Duration::from_millis(req.wait_ms.min(MAX_LEASE_WAIT_MS)).min(s.request_timeout / 2);
    let until = tokio::time::Instant::now() + wait;
    loop {
        // Registered before looking, so that work arriving in between is not missed.
        let woken = s.work.notified();
        tokio::pin!(woken);
        woken.as_mut().enable();
        if let Some(l) = s.lock().lease(&req.worker, Instant::now()) {
            return Ok(Json(l).into_response());
        }
        tokio::select! {
            _ = woken => {}
            _ = tokio::time::sleep_until(until) => {
                s.lock().seen(&req.worker, Instant::now());
                return Ok(StatusCode::NO_CONTENT.into_response());
            }
        }
    }
}

async fn heartbeat(
    State(s): State<AppState>,
    Path((id, chunk)): Path<(String, u32)>,
    body: Bytes,
) -> ApiResult {
    let hb: Heartbeat = json_body(&body, "heartbeat")?;
    let ms = s.lock().heartbeat(&id, chunk, hb.epoch, Instant::now())?;
    Ok(Json(HeartbeatReply { deadline_ms: ms }).into_response())
}

async fn fail(State(s): State<AppState>, Path((id, chunk)): Path<(String, u32)>, body: Bytes) -> ApiResult {
    let f: FailureReport = json_body(&body, "failure report")?;
    s.lock().fail(&id, chunk, f.epoch, &f.error)?;
    s.new_work();
    Ok(StatusCode::NO_CONTENT.into_response())
}

async fn upload(
    State(s): State<AppState>,
    Path((id, chunk)): Path<(String, u32)>,
    RawQuery(q): RawQuery,
    body: Bytes,
) -> ApiResult {
    let epoch = q
        .as_deref()
        .unwrap_or("")
        .split('&')
        .find_map(|kv| kv.strip_prefix("epoch="))
        .and_then(|v| v.parse::<u64>().ok())
        .ok_or_else(|| CoordError::Invalid("the upload needs ?epoch= of its lease".into()))?;
    let coord = s.coord.clone();
    let t = Instant::now();
    metrics::counter!("furnace_upload_bytes_total").increment(body.len() as u64);
    blocking(move || -> Result<(), CoordError> {
        // The lease first; then decode, outside the lock: it is the slow part.
        let max = crate::state::check_upload(&coord, &id, chunk, epoch)?;
        let (acc, stats) = decode_chunk(&body, max).map_err(|e| {
            coord.lock().unwrap_or_else(|e| e.into_inner()).note_refused_upload(&id, chunk, &e.to_string());
            CoordError::Invalid(e.to_string())
        })?;
        crate::state::accept_partial(&coord, &id, chunk, epoch, &acc, stats.as_ref(), Some(&body))
    })
    .await??;
    metrics::histogram!("furnace_upload_duration_seconds").record(t.elapsed().as_secs_f64());
    Ok(StatusCode::NO_CONTENT.into_response())
}

/// Serves until `shutdown` resolves; expires leases every half second.
pub async fn run(
    listener: tokio::net::TcpListener,
    state: AppState,
    shutdown: impl std::future::Future<Output = ()> + Send + 'static,
) -> std::io::Result<()> {
    let s = state.clone();
    tokio::spawn(async move {
        use std::sync::atomic::{AtomicBool, Ordering};
        let syncing = Arc::new(AtomicBool::new(false));
        let mut tick = tokio::time::interval(Duration::from_millis(500));
        for n in 0u64.. {
            tick.tick().await;
            if n % 10 == 0 {
                if let Some(h) = prometheus() {
                    h.run_upkeep();
                }
            }
            if s.lock().expire_leases(Instant::now()) > 0 {
                s.new_work();
            }
            // Rows changed by leases (a job running now), or not stored yet; one sync at a
            // time (a database that stalls does not fill the blocking pool with them).
            if s.lock().rows_due() && !syncing.swap(true, Ordering::AcqRel) {
                let (coord, syncing) = (s.coord.clone(), syncing.clone());
                tokio::task::spawn_blocking(move || {
                    if let Err(e) = crate::state::sync_rows(&coord) {
                        tracing::warn!("cannot store the jobs' rows: {e}");
                    }
                    syncing.store(false, Ordering::Release);
                });
            }
            if n % 4 == 0 {
                let coord = s.coord.clone();
                tokio::task::spawn_blocking(move || crate::state::retry_checkpoints(&coord));
            }
            if n % 60 == 30 {
                let coord = s.coord.clone();
                tokio::task::spawn_blocking(move || crate::state::set_aside_idle(&coord));
            }
            if n % 7200 == 0 && s.unused_files >= UNUSED_FILES_AT_LEAST {
                let (store, age) = (s.store.clone(), s.unused_files);
                tokio::task::spawn_blocking(move || {
                    if let Err(e) = store.collect_garbage(age) {
                        tracing::warn!("collecting unused files: {e}");
                    }
                });
            }
        }
    });
    let (closing, cap, timeout) = (state.closing.clone(), state.max_connections, state.header_timeout);
    let app = router(state);
    // Each connection holds a slot; when all are taken, new ones wait in the listen backlog.
    let slots = Arc::new(tokio::sync::Semaphore::new(cap));
    let mut shutdown = std::pin::pin!(shutdown);
    loop {
        let slot = tokio::select! {
            s = slots.clone().acquire_owned() => s.map_err(std::io::Error::other)?,
            _ = &mut shutdown => break,
        };
        let stream = tokio::select! {
            accepted = listener.accept() => match accepted {
                Ok((stream, _)) => stream,
                Err(e) => {
                    // Out of file descriptors and the like: wait, then go on.
                    tracing::warn!("accept: {e}");
                    tokio::time::sleep(Duration::from_millis(100)).await;
                    continue;
                }
            },
            _ = &mut shutdown => break,
        };
        tokio::spawn(serve_connection(stream, app.clone(), timeout, closing.subscribe(), slot));
    }
    // Stop: open event streams end, idle connections close, requests in flight finish.
    closing.send_replace(true);
    // At most a minute: a client trickling a request must not hold the exit.
    let drained = tokio::time::timeout(SHUTDOWN_DRAIN, slots.acquire_many(cap as u32)).await;
    if drained.is_err() {
        tracing::warn!("stopping with requests still open after {SHUTDOWN_DRAIN:?}");
    }
    Ok(())
}

/// Time a request may take, reading its body included (a 256 MiB body at 4 MB/s fits).
pub const REQUEST_TIMEOUT: Duration = Duration::from_secs(120);

/// How long shutdown waits for requests in flight.
pub const SHUTDOWN_DRAIN: Duration = Duration::from_secs(60);

/// Connections served at once.
pub const MAX_CONNECTIONS: usize = 512;
/// Time a client has to send a request's headers once it has started it.
pub const HEADER_READ_TIMEOUT: Duration = Duration::from_secs(10);

async fn serve_connection(
    stream: tokio::net::TcpStream,
    app: Router,
    header_timeout: Duration,
    mut closing: tokio::sync::watch::Receiver<bool>,
    _slot: tokio::sync::OwnedSemaphorePermit,
) {
    let mut http = hyper::server::conn::http1::Builder::new();
    http.timer(hyper_util::rt::TokioTimer::new()).header_read_timeout(header_timeout);
    let service = hyper_util::service::TowerToHyperService::new(app);
    let mut conn = std::pin::pin!(http.serve_connection(hyper_util::rt::TokioIo::new(stream), service));
    let mut stopping = *closing.borrow_and_update();
    if stopping {
        conn.as_mut().graceful_shutdown();
    }
    loop {
        tokio::select! {
            _ = conn.as_mut() => break,
            changed = closing.changed(), if !stopping => {
                stopping = true;
                if changed.is_ok() {
                    conn.as_mut().graceful_shutdown();
                }
            }
        }
    }
}
