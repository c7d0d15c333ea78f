//! The shared-memory data plane end to end: a session created over gRPC, stepped through its
//! region and doorbell, gives exactly the Batches a twin session gives over gRPC; bad actions
//! and unknown sessions are refused with gRPC's code and message; a client that goes ends its
//! session's thread and frees the region's budget.
//!
//! And whom it trusts: a hello with a wrong secret is refused exactly as an unknown ID (also
//! across tenants, on the real binary); another user's connection is closed before any thread
//! starts (the real binary, and a second user made here when the test runs as root), while a
//! client the server cannot see in its pid namespace is served, and a server run as nobody
//! offers no doorbell at all; silent connections past the cap are closed at once; a planner
//! session's Steps wait for the CPU pool.
//!
//! And how they are served: the sessions of one client process by one thread, in turn, a
//! planner's by a thread of its own.
#![cfg(target_os = "linux")]

use crate::binary_support;
use crate::grpc_support;

use std::io::{IoSlice, IoSliceMut};
use std::mem::MaybeUninit;
use std::os::fd::OwnedFd;
use std::sync::Arc;
use std::time::{Duration, Instant};

use binary_support::Process;
use dinerdash_server::budget::{Share, Tenant};
use dinerdash_server::pb::{self, diner_dash_client::DinerDashClient};
use dinerdash_server::pools::{CpuPool, Turn};
use dinerdash_server::server::ServerConfig;
use dinerdash_server::shm::layout::{FIELDS, Layout};
use dinerdash_server::shm::{HELLO_BYTES, MAX_PENDING_HELLOS};
use grpc_support::{
    Actions, PATIENCE, TestServer, create_request, metric, pack, reset, scrape, step,
};
use rustix::net::{
    AddressFamily, RecvAncillaryBuffer, RecvAncillaryMessage, RecvFlags, SendAncillaryBuffer,
    SendFlags, SocketAddrUnix, SocketFlags, SocketType,
};

/// A client's end of the doorbell and its region.
struct ShmClient {
    sock: OwnedFd,
    region: OwnedFd,
    layout: Layout,
}

/// A connection to `doorbell` that has said nothing yet.
fn silent(doorbell: &str) -> OwnedFd {
    let sock = rustix::net::socket_with(
        AddressFamily::UNIX,
        SocketType::SEQPACKET,
        SocketFlags::CLOEXEC,
        None,
    )
    .unwrap();
    let addr = SocketAddrUnix::new_abstract_name(doorbell.as_bytes()).unwrap();
    rustix::net::connect(&sock, &addr).unwrap();
    sock
}

/// Connects to `doorbell` and says hello for `session` with `secret`: the region, or the `E`
/// message.
fn connect(doorbell: &str, session: &str, secret: &[u8]) -> Result<ShmClient, Vec<u8>> {
    hello(
        doorbell,
        &[b"H".as_slice(), session.as_bytes(), secret].concat(),
    )
}

/// Connects to `doorbell` and sends `hello` as it is: the region, or the `E` message (empty
/// when the server closed the connection unanswered).
fn hello(doorbell: &str, hello: &[u8]) -> Result<ShmClient, Vec<u8>> {
    let sock = silent(doorbell);
    match rustix::net::sendmsg(
        &sock,
        &[IoSlice::new(hello)],
        &mut SendAncillaryBuffer::default(),
        SendFlags::NOSIGNAL,
    ) {
        Ok(_) => {}
        // Closed before the hello arrived (a connection past the cap): as no reply.
        Err(rustix::io::Errno::PIPE | rustix::io::Errno::CONNRESET) => return Err(Vec::new()),
        Err(e) => panic!("sendmsg: {e}"),
    }
    let mut reply = [0u8; 4096];
    let mut space = [MaybeUninit::uninit(); rustix::cmsg_space!(ScmRights(1))];
    let mut control = RecvAncillaryBuffer::new(&mut space);
    let got = match rustix::net::recvmsg(
        &sock,
        &mut [IoSliceMut::new(&mut reply)],
        &mut control,
        RecvFlags::empty(),
    ) {
        Ok(got) => got,
        // Closed unanswered with the hello unread (a connection past the cap): as no reply.
        Err(rustix::io::Errno::CONNRESET) => return Err(Vec::new()),
        Err(e) => panic!("recvmsg: {e}"),
    };
    let mut fds = Vec::new();
    for message in control.drain() {
        if let RecvAncillaryMessage::ScmRights(rights) = message {
            fds.extend(rights);
        }
    }
    if reply[0] != b'R' {
        return Err(reply[..got.bytes].to_vec());
    }
    let region = fds.pop().expect("a memfd with R");
    let mut header = [0u8; 16];
    rustix::io::pread(&region, &mut header, 0).unwrap();
    assert_eq!(&header[..4], b"DDsh");
    let n = u32::from_le_bytes(header[8..12].try_into().unwrap()) as usize;
    Ok(ShmClient {
        sock,
        region,
        layout: Layout::new(n),
    })
}

impl ShmClient {
    /// One Step: `Ok` with the region's arrays by name, or the `E` message.
    fn step(&self, actions: &[i32]) -> Result<Vec<(String, Vec<u8>)>, Vec<u8>> {
        self.ring(actions);
        self.reply()
    }

    /// Writes a Step's actions and rings, without waiting for the reply.
    fn ring(&self, actions: &[i32]) {
        let (offset, _) = self.layout.actions();
        rustix::io::pwrite(&self.region, &pack(actions), offset as u64).unwrap();
        rustix::net::send(&self.sock, b"S", SendFlags::empty()).unwrap();
    }

    /// The reply to the Step rung for: as [`ShmClient::step`].
    fn reply(&self) -> Result<Vec<(String, Vec<u8>)>, Vec<u8>> {
        let mut reply = [0u8; 4096];
        let (n, _) = rustix::net::recv(&self.sock, &mut reply, RecvFlags::empty()).unwrap();
        if reply[..n] != *b"K" {
            return Err(reply[..n].to_vec());
        }
        let mut lengths = [0u8; 4 * FIELDS.len()];
        rustix::io::pread(&self.region, &mut lengths, Layout::length_at(0) as u64).unwrap();
        Ok(FIELDS
            .iter()
            .enumerate()
            .skip(1)
            .map(|(i, &(name, _))| {
                let len = u32::from_le_bytes(lengths[4 * i..4 * i + 4].try_into().unwrap());
                let mut bytes = vec![0u8; len as usize];
                let offset = self.layout.arrays[i].0 as u64;
                rustix::io::pread(&self.region, &mut bytes, offset).unwrap();
                (name.to_owned(), bytes)
            })
            .collect())
    }
}

/// The arrays of a gRPC Batch by their names, as the region holds them.
fn arrays(b: &pb::Batch) -> Vec<(String, Vec<u8>)> {
    let seeds: Vec<u8> = b.seeds.iter().flat_map(|s| s.to_le_bytes()).collect();
    let episodes: Vec<u8> = b
        .stream_episodes
        .iter()
        .flat_map(|s| s.to_le_bytes())
        .collect();
    let fields: [&[u8]; 18] = [
        &b.observations,
        &b.rewards,
        &b.terminated,
        &b.truncated,
        &b.scores,
        &b.lost,
        &b.ticks,
        &b.action_masks,
        &b.expert_actions,
        &b.reset,
        &seeds,
        &episodes,
        &b.final_observations,
        &b.final_scores,
        &b.final_lost,
        &b.final_ticks,
        &b.final_action_masks,
        &b.final_expert_actions,
    ];
    FIELDS[1..]
        .iter()
        .zip(fields)
        .map(|(&(name, _), bytes)| (name.to_owned(), bytes.to_vec()))
        .collect()
}

/// The `E` message's gRPC code and message.
fn refusal(e: &[u8]) -> (i32, String) {
    assert_eq!(e[0], b'E');
    let code = i32::from_le_bytes(e[1..5].try_into().unwrap());
    let len = u32::from_le_bytes(e[5..9].try_into().unwrap()) as usize;
    (code, String::from_utf8(e[9..9 + len].to_vec()).unwrap())
}

fn config() -> ServerConfig {
    ServerConfig {
        max_shm_sessions: 2,
        ..ServerConfig::default()
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_region_steps_exactly_as_grpc_in_every_autoreset_mode() {
    let server = TestServer::start_with(config(), false).await;
    let mut client = server.client().await;
    for mode in [
        pb::AutoresetMode::NextStep,
        pb::AutoresetMode::SameStep,
        pb::AutoresetMode::Disabled,
    ] {
        let mut ids = Vec::new();
        let mut secrets = Vec::new();
        let mut doorbell = String::new();
        for _ in 0..2 {
            let mut request = create_request(5, mode, Some(7));
            // Short episodes, so that autoresets happen within the test.
            request.config = Some(pb::GameConfig {
                lives: Some(1),
                time_limit: Some(40),
                ..Default::default()
            });
            let reply = client.create_session(request).await.unwrap().into_inner();
            doorbell = reply.shm_doorbell;
            ids.push(reply.session_id);
            secrets.push(reply.shm_secret);
        }
        assert!(doorbell.starts_with("dinerdash-"), "{doorbell:?}");
        let (over_shm, over_grpc) = (&ids[0], &ids[1]);
        reset(&mut client, over_shm, None).await;
        reset(&mut client, over_grpc, None).await;
        let shm =
            tokio::task::block_in_place(|| connect(&doorbell, over_shm, &secrets[0])).unwrap();
        let mut actions = Actions::new(3);
        for k in 0..120 {
            let a: Vec<i32> = (0..5).map(|_| actions.next()).collect();
            let twin = step(&mut client, over_grpc, &a).await;
            let stepped = tokio::task::block_in_place(|| shm.step(&a));
            assert_eq!(stepped.unwrap(), arrays(&twin), "{mode:?}, step {k}");
            let ended = twin
                .terminated
                .iter()
                .chain(&twin.truncated)
                .any(|&d| d == 1);
            if mode == pb::AutoresetMode::Disabled && ended {
                break;
            }
        }
        // The next step of an ended DISABLED episode is refused as over gRPC.
        if mode == pb::AutoresetMode::Disabled {
            let e = tokio::task::block_in_place(|| shm.step(&[0; 5])).unwrap_err();
            assert_eq!(refusal(&e).0, tonic::Code::FailedPrecondition as i32);
        }
    }
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn bad_actions_and_unknown_sessions_are_refused_as_over_grpc() {
    let server = TestServer::start_with(config(), false).await;
    let mut client = server.client().await;
    let reply = client
        .create_session(create_request(3, pb::AutoresetMode::NextStep, Some(1)))
        .await
        .unwrap()
        .into_inner();
    let id = reply.session_id;
    let secret = reply.shm_secret;
    reset(&mut client, &id, None).await;
    let shm = tokio::task::block_in_place(|| connect(&reply.shm_doorbell, &id, &secret)).unwrap();
    let refused = tokio::task::block_in_place(|| shm.step(&[0, 57, 0])).unwrap_err();
    let grpc = client
        .step(pb::StepRequest {
            session_id: id.clone(),
            actions: pack(&[0, 57, 0]),
        })
        .await
        .unwrap_err();
    assert_eq!(
        refusal(&refused),
        (grpc.code() as i32, grpc.message().to_owned())
    );
    // The refused step changed nothing: the session still steps.
    assert!(tokio::task::block_in_place(|| shm.step(&[0, 0, 0])).is_ok());

    let unknown = "0".repeat(32);
    let e = tokio::task::block_in_place(|| connect(&reply.shm_doorbell, &unknown, &secret))
        .err()
        .unwrap();
    assert_eq!(refusal(&e).0, tonic::Code::NotFound as i32);

    // --max-shm-sessions 2: a third region is refused, and given back when a client goes.
    let other = tokio::task::block_in_place(|| connect(&reply.shm_doorbell, &id, &secret)).unwrap();
    let e = tokio::task::block_in_place(|| connect(&reply.shm_doorbell, &id, &secret))
        .err()
        .unwrap();
    assert_eq!(refusal(&e).0, tonic::Code::ResourceExhausted as i32);
    drop(other);
    let deadline = Instant::now() + PATIENCE;
    loop {
        match tokio::task::block_in_place(|| connect(&reply.shm_doorbell, &id, &secret)) {
            Ok(_) => break,
            Err(_) if Instant::now() < deadline => {
                tokio::time::sleep(Duration::from_millis(20)).await;
            }
            Err(e) => panic!("the slot never came back: {:?}", refusal(&e)),
        }
    }

    // A session closed over gRPC: its region's next step says NOT_FOUND.
    client
        .close_session(pb::CloseSessionRequest {
            session_id: id.clone(),
        })
        .await
        .unwrap();
    let e = tokio::task::block_in_place(|| shm.step(&[0, 0, 0])).unwrap_err();
    assert_eq!(refusal(&e).0, tonic::Code::NotFound as i32);
    server.stop().await;
}

/// The refusal of a hello for session `id` with `secret` at `doorbell`: the `E` message's code,
/// and its message with `id` written as `<id>` (what an unknown ID and a wrong secret must both
/// give).
fn refused_at(doorbell: &str, id: &str, secret: &[u8]) -> (i32, String) {
    let e = tokio::task::block_in_place(|| connect(doorbell, id, secret))
        .err()
        .expect("refused");
    let (code, message) = refusal(&e);
    (code, message.replace(id, "<id>"))
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_wrong_secret_is_refused_exactly_as_an_unknown_id() {
    let server = TestServer::start_with(config(), true).await;
    let mut client = server.client().await;
    let mut made = Vec::new();
    for _ in 0..2 {
        let request = create_request(2, pb::AutoresetMode::NextStep, Some(3));
        made.push(client.create_session(request).await.unwrap().into_inner());
    }
    let (a, b) = (&made[0], &made[1]);
    assert_eq!(a.shm_secret.len(), 32);
    assert_ne!(a.shm_secret, b.shm_secret);
    assert_eq!(a.shm_server_pid, std::process::id());
    // The reply's Debug shows no byte of the secret.
    let shown = format!("{a:?}");
    assert!(shown.contains("<32 bytes redacted>"), "{shown}");
    assert!(!shown.contains(&format!("{:?}", a.shm_secret)), "{shown}");

    let doorbell = a.shm_doorbell.clone();
    let refused = |id: &str, secret: &[u8]| refused_at(&doorbell, id, secret);
    let unknown = "0123456789abcdef0123456789abcdef";
    let as_unknown = refused(unknown, &a.shm_secret);
    let grpc = client
        .step(pb::StepRequest {
            session_id: unknown.into(),
            actions: pack(&[0, 0]),
        })
        .await
        .unwrap_err();
    assert_eq!(
        as_unknown,
        (grpc.code() as i32, grpc.message().replace(unknown, "<id>"))
    );
    let mut flipped = a.shm_secret.clone();
    flipped[31] ^= 1;
    for secret in [b.shm_secret.clone(), vec![0; 32], flipped] {
        assert_eq!(refused(&a.session_id, &secret), as_unknown);
    }
    // A client older than the secret (`H` and the ID only): refused, told why.
    let old = [b"H".as_slice(), a.session_id.as_bytes()].concat();
    let e = tokio::task::block_in_place(|| hello(&doorbell, &old))
        .err()
        .unwrap();
    let (code, message) = refusal(&e);
    assert_eq!(code, tonic::Code::InvalidArgument as i32);
    assert!(message.contains("shm_secret"), "{message}");
    assert!(message.contains(&HELLO_BYTES.to_string()), "{message}");
    // Counted as gRPC counts its refusals: 4 over shared memory, 1 over gRPC.
    let text = scrape(server.metrics_addr.unwrap()).await;
    assert_eq!(
        metric(&text, "dinerdash_rpc_errors_total{code=\"NOT_FOUND\"}"),
        5
    );
    // The session's own secret still opens it.
    reset(&mut client, &a.session_id, None).await;
    let shm =
        tokio::task::block_in_place(|| connect(&doorbell, &a.session_id, &a.shm_secret)).unwrap();
    assert!(tokio::task::block_in_place(|| shm.step(&[0, 0])).is_ok());
    server.stop().await;
}

/// Threads of process `pid` other than tokio's (`tokio-rt-worker`: its workers, and its blocking
/// threads, which the session sweeper starts and ends on its own schedule).
fn threads(pid: u32) -> usize {
    threads_where(pid, |name| name != "tokio-rt-worker")
}

/// Threads of process `pid` named `name`.
fn threads_named(pid: u32, name: &str) -> usize {
    threads_where(pid, |n| n == name)
}

/// Threads of process `pid` whose name passes `keep`, read in one pass over /proc.
fn threads_where(pid: u32, keep: impl Fn(&str) -> bool) -> usize {
    std::fs::read_dir(format!("/proc/{pid}/task"))
        .unwrap()
        .filter_map(Result::ok)
        .filter(|task| {
            std::fs::read_to_string(task.path().join("comm")).is_ok_and(|c| keep(c.trim()))
        })
        .count()
}

/// A client run as another user: connects to the doorbell (argv 1), sends the hello (argv 2,
/// hex) and prints the reply in hex: nothing when the server closed the connection unanswered.
const OTHER_USER_CLIENT: &str = r#"
import socket, sys
s = socket.socket(socket.AF_UNIX, socket.SOCK_SEQPACKET)
s.settimeout(60)
s.connect("\0" + sys.argv[1])
try:
    s.sendall(bytes.fromhex(sys.argv[2]))
    reply = s.recv(4096)
except (BrokenPipeError, ConnectionResetError):
    reply = b""
print(reply.hex(), flush=True)
"#;

/// Creates a session of `num_envs` and resets it: the creation's reply.
async fn created(
    client: &mut DinerDashClient<tonic::transport::Channel>,
    num_envs: u32,
) -> pb::CreateSessionResponse {
    let request = create_request(num_envs, pb::AutoresetMode::NextStep, Some(11));
    let reply = client.create_session(request).await.unwrap().into_inner();
    reset(client, &reply.session_id, None).await;
    reply
}

/// The environment variable that lets a test needing root be skipped when not root, instead of
/// failing: `DINERDASH_SKIP_ROOT_TESTS=1` (CI runs as root and never sets it).
const SKIP_ROOT_TESTS: &str = "DINERDASH_SKIP_ROOT_TESTS";

/// Whether this test, which needs root (`why`), may run: yes as root; when not root, it fails
/// unless [`SKIP_ROOT_TESTS`] is `1`, which skips it (saying so), so that a run that is not
/// root never passes a test it did not run.
fn root_or_opted_out(why: &str) -> bool {
    if rustix::process::geteuid().is_root() {
        return true;
    }
    if std::env::var(SKIP_ROOT_TESTS).is_ok_and(|v| v == "1") {
        eprintln!("skipped ({SKIP_ROOT_TESTS}=1): {why}");
        return false;
    }
    panic!("this test needs root: {why}; run it as root, or set {SKIP_ROOT_TESTS}=1 to skip it");
}

fn hex(bytes: &[u8]) -> String {
    bytes.iter().map(|b| format!("{b:02x}")).collect()
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn another_users_connection_is_closed_before_any_thread_starts() {
    use std::os::unix::process::CommandExt;
    if !root_or_opted_out(
        "running a client as a second user (uid 65534) needs root (CI runs as \
             root); the peer check itself is unit-tested in shm::tests",
    ) {
        return;
    }
    let server = Process::start("", "--max-shm-sessions 4");
    let mut client = DinerDashClient::connect(format!("http://{}", server.addr))
        .await
        .unwrap();
    let reply = created(&mut client, 1).await;
    let pid = server.pid();
    let before = threads(pid);
    // Another user, even with the session's ID and secret: closed, unanswered, no thread.
    let hello = [
        b"H".as_slice(),
        reply.session_id.as_bytes(),
        &reply.shm_secret,
    ]
    .concat();
    let (doorbell, hello) = (reply.shm_doorbell.clone(), hex(&hello));
    let out = tokio::task::spawn_blocking(move || {
        std::process::Command::new("python3")
            .args(["-c", OTHER_USER_CLIENT, &doorbell, &hello])
            .current_dir("/")
            .uid(65534)
            .gid(65534)
            .output()
            .unwrap()
    })
    .await
    .unwrap();
    let stderr = String::from_utf8_lossy(&out.stderr);
    assert!(out.status.success(), "{stderr}");
    let answer = String::from_utf8_lossy(&out.stdout);
    assert_eq!(answer.trim(), "", "another user was answered");
    assert_eq!(threads_named(pid, "shm-session"), 0);
    assert!(
        threads(pid) <= before,
        "{} threads, {before} before",
        threads(pid)
    );
    // The owner gets in: its thread, and its region.
    let shm = tokio::task::block_in_place(|| {
        connect(&reply.shm_doorbell, &reply.session_id, &reply.shm_secret)
    })
    .unwrap();
    assert!(tokio::task::block_in_place(|| shm.step(&[0])).is_ok());
    assert_eq!(threads_named(pid, "shm-session"), 1);
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_client_the_server_cannot_see_in_its_pid_namespace_is_served() {
    if !root_or_opted_out(
        "a server in a pid namespace of its own needs root (CI runs as root); \
             reading a peer without a pid is unit-tested in shm::tests",
    ) {
        return;
    }
    // The server in a pid namespace of its own (as in a container that shares the host's
    // network), this test outside it: the kernel tells the server pid 0 for this process.
    // Such a client was closed as "another user" (the peer read failed).
    let server = Process::start_under(
        "unshare --pid --fork --kill-child",
        env!("CARGO_BIN_EXE_dinerdash-server"),
        "--max-shm-sessions 4",
    );
    let mut client = DinerDashClient::connect(format!("http://{}", server.addr))
        .await
        .unwrap();
    let reply = created(&mut client, 2).await;
    // The first process of its own pid namespace: this test's process is outside it.
    assert_eq!(reply.shm_server_pid, 1);
    let id = reply.session_id.clone();
    let shm = tokio::task::block_in_place(|| {
        connect(&reply.shm_doorbell, &reply.session_id, &reply.shm_secret)
    })
    .expect("served");
    // Served alone (it has no pid to be grouped by), and stepped as over gRPC.
    let twin = created(&mut client, 2).await.session_id;
    reset(&mut client, &id, Some(5)).await;
    reset(&mut client, &twin, Some(5)).await;
    for t in 0..20 {
        let actions = [t % 57, (3 * t) % 57];
        let got = tokio::task::block_in_place(|| shm.step(&actions)).unwrap();
        assert_eq!(got, arrays(&step(&mut client, &twin, &actions).await));
    }
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_server_run_as_nobody_offers_no_shared_memory() {
    use std::os::unix::fs::PermissionsExt;
    if !root_or_opted_out(
        "running the server as nobody (kernel.overflowuid) needs root (CI runs as \
             root); the owner check itself is unit-tested in shm::tests",
    ) {
        return;
    }
    // The kernel reports every peer it cannot map (a process of another user namespace) as
    // nobody: a server running as nobody could not tell its own clients from strangers.
    let nobody = std::fs::read_to_string("/proc/sys/kernel/overflowuid").unwrap();
    let nobody = nobody.trim();
    // A copy of the binary nobody may run (the build directory may be private).
    let exe = std::env::temp_dir().join(format!("dinerdash-server-nobody-{}", std::process::id()));
    std::fs::copy(env!("CARGO_BIN_EXE_dinerdash-server"), &exe).unwrap();
    std::fs::set_permissions(&exe, std::fs::Permissions::from_mode(0o755)).unwrap();
    let server = Process::start_under(
        &format!("setpriv --reuid={nobody} --regid={nobody} --clear-groups"),
        exe.to_str().unwrap(),
        "--max-shm-sessions 4",
    );
    let _ = std::fs::remove_file(&exe); // running: the file is no longer needed
    let mut client = DinerDashClient::connect(format!("http://{}", server.addr))
        .await
        .unwrap();
    let reply = created(&mut client, 1).await;
    assert_eq!(
        reply.shm_doorbell, "",
        "a doorbell offered by a server run as nobody"
    );
    // Stepping over gRPC is unaffected.
    step(&mut client, &reply.session_id, &[0]).await;
    server.signal("-KILL"); // no drain to wait for
    let (_, stderr) = tokio::task::spawn_blocking(move || server.wait())
        .await
        .unwrap();
    assert!(stderr.contains("kernel.overflowuid"), "{stderr}");
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn silent_connections_past_the_cap_are_closed_at_once() {
    let server = TestServer::start_with(config(), false).await;
    let mut client = server.client().await;
    let reply = created(&mut client, 1).await;
    let doorbell = reply.shm_doorbell.clone();
    tokio::task::block_in_place(|| {
        let waiting: Vec<OwnedFd> = (0..MAX_PENDING_HELLOS).map(|_| silent(&doorbell)).collect();
        let extra = silent(&doorbell);
        rustix::net::sockopt::set_socket_timeout(
            &extra,
            rustix::net::sockopt::Timeout::Recv,
            Some(PATIENCE),
        )
        .unwrap();
        let mut buf = [0u8; 64];
        let (n, _) = rustix::net::recv(&extra, &mut buf, RecvFlags::empty()).unwrap();
        assert_eq!(n, 0, "the connection past the cap is closed without a word");
        // Those within the cap still wait for their hello (for seconds, not closed yet).
        for sock in &waiting {
            assert_eq!(
                rustix::net::recv(sock, &mut buf, RecvFlags::DONTWAIT).unwrap_err(),
                rustix::io::Errno::AGAIN
            );
        }
    });
    // Once they are gone, a client with its hello gets in.
    let deadline = Instant::now() + PATIENCE;
    let shm = loop {
        match tokio::task::block_in_place(|| {
            connect(&doorbell, &reply.session_id, &reply.shm_secret)
        }) {
            Ok(shm) => break shm,
            Err(_) if Instant::now() < deadline => {
                tokio::time::sleep(Duration::from_millis(20)).await;
            }
            Err(e) => panic!("never let in: {e:?}"),
        }
    };
    assert!(tokio::task::block_in_place(|| shm.step(&[0])).is_ok());
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn a_planner_sessions_steps_wait_for_the_cpu_pool() {
    let server = TestServer::start_with(config(), false).await;
    let mut client = server.client().await;
    let mut request = create_request(1, pb::AutoresetMode::NextStep, Some(5));
    request.expert_policy = pb::Policy::Planner.into();
    let planner = client.create_session(request).await.unwrap().into_inner();
    reset(&mut client, &planner.session_id, None).await;
    let plain = created(&mut client, 1).await;
    let doorbell = planner.shm_doorbell.clone();
    let (p, q) = tokio::task::block_in_place(|| {
        (
            connect(&doorbell, &planner.session_id, &planner.shm_secret).unwrap(),
            connect(&doorbell, &plain.session_id, &plain.shm_secret).unwrap(),
        )
    });
    // Every worker of the pool the gRPC path uses is taken (by Rollouts, say).
    let pool = CpuPool::beside_steps();
    let holder = Arc::new(Tenant::new("a holder".into(), Share::default()));
    let mut held = Vec::new();
    for _ in 0..pool.workers() {
        held.push(pool.acquire(Turn::of(&holder)).await.unwrap());
    }
    // A session without the planner steps on; the planner's Step waits for a worker.
    assert!(tokio::task::block_in_place(|| q.step(&[0])).is_ok());
    let (tx, rx) = std::sync::mpsc::channel();
    let stepping = std::thread::spawn(move || tx.send(p.step(&[0]).is_ok()).unwrap());
    let early = tokio::task::block_in_place(|| rx.recv_timeout(Duration::from_millis(300)));
    assert!(
        early.is_err(),
        "a planner Step ran while every worker was taken"
    );
    drop(held);
    let stepped = tokio::task::block_in_place(|| rx.recv_timeout(PATIENCE)).unwrap();
    assert!(stepped);
    stepping.join().unwrap();
    server.stop().await;
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn another_tenant_knowing_the_id_but_not_the_secret_is_refused_as_unknown() {
    let dir = std::env::temp_dir().join(format!("dinerdash-shm-tenants-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let file = dir.join("tenants");
    let (token_a, token_b) = ("tenant-a-0123456789abcdef", "tenant-b-0123456789abcdef");
    std::fs::write(&file, format!("team-a {token_a}\nteam-b {token_b}\n")).unwrap();
    let server = Process::start("", &format!("--auth-tokens-file '{}'", file.display()));
    let mut c = DinerDashClient::connect(format!("http://{}", server.addr))
        .await
        .unwrap();
    // Tenant A's session and its undisturbed twin; tenant B's own session.
    let a = created_by(&mut c, token_a).await;
    let twin = created_by(&mut c, token_a).await;
    let b = created_by(&mut c, token_b).await;
    let doorbell = a.shm_doorbell.clone();
    let refused = |id: &str, secret: &[u8]| refused_at(&doorbell, id, secret);
    // B knows A's ID: with its own secret, or a guess, it is told what an unknown ID is told.
    let as_unknown = refused("00000000000000000000000000000000", &b.shm_secret);
    assert_eq!(as_unknown.0, tonic::Code::NotFound as i32);
    assert_eq!(refused(&a.session_id, &b.shm_secret), as_unknown);
    assert_eq!(refused(&a.session_id, &[0; 32]), as_unknown);
    // A's session is untouched: its next Step over shared memory equals its twin's over gRPC.
    let shm =
        tokio::task::block_in_place(|| connect(&doorbell, &a.session_id, &a.shm_secret)).unwrap();
    let step = pb::StepRequest {
        session_id: twin.session_id.clone(),
        actions: pack(&[0, 1]),
    };
    let expected = c.step(with(token_a, step)).await.unwrap().into_inner();
    let stepped = tokio::task::block_in_place(|| shm.step(&[0, 1])).unwrap();
    assert_eq!(stepped, arrays(&expected));
    drop(server);
    std::fs::remove_dir_all(&dir).unwrap();
}

/// `message` with `token` as its bearer token.
fn with<T>(token: &str, message: T) -> tonic::Request<T> {
    let mut request = tonic::Request::new(message);
    let value = format!("Bearer {token}").parse().unwrap();
    request.metadata_mut().insert("authorization", value);
    request
}

/// A session of 2 environments (seed 9) created and reset (seed 4) by `token`'s tenant.
async fn created_by(
    c: &mut DinerDashClient<tonic::transport::Channel>,
    token: &str,
) -> pb::CreateSessionResponse {
    let request = create_request(2, pb::AutoresetMode::NextStep, Some(9));
    let reply = c
        .create_session(with(token, request))
        .await
        .unwrap()
        .into_inner();
    let reset = pb::ResetRequest {
        session_id: reply.session_id.clone(),
        seed: Some(4),
        ..Default::default()
    };
    c.reset(with(token, reset)).await.unwrap();
    reply
}

#[tokio::test(flavor = "multi_thread", worker_threads = 2)]
async fn one_thread_serves_a_client_processs_sessions_and_a_planners_has_its_own() {
    let server = Process::start("", "--max-shm-sessions 8");
    let pid = server.pid();
    let mut c = DinerDashClient::connect(format!("http://{}", server.addr))
        .await
        .unwrap();
    // Three sessions of this process, each with a twin stepped over gRPC.
    let mut pairs = Vec::new();
    for _ in 0..3 {
        pairs.push((created(&mut c, 2).await, created(&mut c, 2).await));
    }
    let doorbell = pairs[0].0.shm_doorbell.clone();
    let shm: Vec<ShmClient> = tokio::task::block_in_place(|| {
        pairs
            .iter()
            .map(|(s, _)| connect(&doorbell, &s.session_id, &s.shm_secret).unwrap())
            .collect()
    });
    // Every session rung before any reply is read (pipelined), many times over: each gets its
    // own Step's reply, equal to its twin's over gRPC.
    let mut actions = Actions::new(8);
    for k in 0..60 {
        let a: Vec<Vec<i32>> = (0..3)
            .map(|_| (0..2).map(|_| actions.next()).collect())
            .collect();
        tokio::task::block_in_place(|| shm.iter().zip(&a).for_each(|(s, a)| s.ring(a)));
        for ((s, (_, twin)), a) in shm.iter().zip(&pairs).zip(&a) {
            let expected = step(&mut c, &twin.session_id, a).await;
            let got = tokio::task::block_in_place(|| s.reply()).unwrap();
            assert_eq!(got, arrays(&expected), "step {k}");
        }
    }
    // The hello threads of the second and third sessions handed them over and ended.
    assert_eq!(shm_threads_settle_at(pid, 1).await, 1);
    // A planner's session: a thread of its own (its Steps may wait for the CPU pool).
    let mut request = create_request(1, pb::AutoresetMode::NextStep, Some(5));
    request.expert_policy = pb::Policy::Planner.into();
    let planner = c.create_session(request).await.unwrap().into_inner();
    reset(&mut c, &planner.session_id, None).await;
    let p = tokio::task::block_in_place(|| {
        connect(&doorbell, &planner.session_id, &planner.shm_secret).unwrap()
    });
    assert!(tokio::task::block_in_place(|| p.step(&[0])).is_ok());
    assert_eq!(shm_threads_settle_at(pid, 2).await, 2);
    // A session closed over gRPC while its client's others keep stepping is let go: its
    // doorbell hangs up (its region and slot with it).
    c.close_session(pb::CloseSessionRequest {
        session_id: pairs[0].0.session_id.clone(),
    })
    .await
    .unwrap();
    let hung_up = tokio::task::block_in_place(|| {
        let deadline = Instant::now() + PATIENCE;
        loop {
            for s in &shm[1..] {
                assert!(s.step(&[0, 0]).is_ok());
            }
            let mut byte = [0u8; 1];
            match rustix::net::recv(&shm[0].sock, &mut byte, RecvFlags::DONTWAIT) {
                Ok((0, _)) => return true,
                _ if Instant::now() > deadline => return false,
                _ => std::thread::sleep(Duration::from_millis(5)),
            }
        }
    });
    assert!(hung_up, "a closed session's doorbell stayed open");
    // When the client's sessions go, so does their thread.
    drop(shm);
    assert_eq!(shm_threads_settle_at(pid, 1).await, 1);
}

/// The server's `shm-session` threads once their count is `want` (a thread that has just
/// returned may still be listed for a moment), or after the test's patience.
async fn shm_threads_settle_at(pid: u32, want: usize) -> usize {
    let deadline = Instant::now() + PATIENCE;
    loop {
        let now = threads_named(pid, "shm-session");
        if now == want || Instant::now() > deadline {
            return now;
        }
        tokio::time::sleep(Duration::from_millis(10)).await;
    }
}
