//! The same-host data plane: a client on the server's machine, running as the server's user,
//! steps its session through shared memory instead of gRPC (docs/shm.md).
//!
//! The session is created, reset, forked, closed and expired over gRPC as always; only Step
//! moves. CreateSession names the server's *doorbell*, an abstract-namespace Unix socket
//! (`SOCK_SEQPACKET`: no file to leak, reachable only from this host's network namespace), and
//! tells its creator, and only it, the session's secret and this process's pid.
//!
//! Whom it trusts: only processes of the server's own user, and of those only the creator of a
//! session (who holds its secret). Any local user can connect to an abstract socket, so the
//! acceptor checks the peer's uid (`SO_PEERCRED`) right after `accept`, before it starts a
//! thread or allocates anything: another user's connection is closed at once, unanswered. At
//! most [`MAX_PENDING_HELLOS`] connections of the owner may wait for their hello at once (each
//! holds a thread for up to [`HELLO_TIMEOUT`]); one more is closed at once too. The hello is
//! `H`, the session ID and the session's 32-byte secret; a wrong secret is refused exactly as an
//! unknown ID (NOT_FOUND, the same message: [`crate::session::Store::find_shm`]), and every
//! later Step looks the session up by the same ID and secret. Then the server creates the
//! session's [`region::Region`] (a memfd laid out by [`layout`]) and passes its descriptor back
//! (`SCM_RIGHTS`). From then on each Step is one message each way: the client writes the
//! actions into the region and sends `S`; its client's thread copies them out, steps the
//! session exactly as the gRPC Step does (same checks, same errors: `E`, the gRPC code, the
//! message and the encoded `google.rpc.Status` details, counted in the metrics' error counter),
//! writes the reply's arrays into the region and answers `K`. A planner session's Steps wait
//! for a permit of the bounded CPU pool the gRPC path uses ([`crate::service::step_path`]).
//!
//! Why a socket and not a futex or an eventfd: one `poll` wakes the thread and tells it when the
//! client died (the socket closes with the process, `kill -9` included), and the handshake, the
//! descriptor passing and the peer check come with it.
//!
//! Who steps: one std thread per *client process* (the peer's pid, `SO_PEERCRED`) serves all
//! its sessions in turn ([`serve`]); a later session's hello thread hands the session over to
//! it ([`Client::join`]) and ends. A planner session, whose Steps may wait for the CPU pool,
//! gets a thread of its own, so that its waits hold up none of its client's other sessions, and
//! so does each session of a client whose pid this server cannot see (another pid namespace:
//! [`Peer::pid`]).
//! Why a std thread rather than a tokio task: the step is synchronous CPU work of tens of
//! microseconds, and a blocked thread wakes within one context switch. Why one per client
//! process rather than per session: a client that pipelines (`step_async` on one session while
//! it decodes another's reply) rings a thread that is stepping or polling, not one asleep, and
//! ringing a sleeping thread costs the client tens of microseconds on a virtual machine (its
//! wake-up); the thread steps the sessions one after another, which is as fast as a Python
//! client's decoding of them anyway (docs/benchmarks.md). A thread can only ever slow its own
//! client's sessions. `--max-shm-sessions` bounds the sessions and the regions (and so the
//! threads; [`MAX_PENDING_HELLOS`] bounds the threads still waiting for a hello); the regions
//! count in the memory budget.
//!
//! Why the thread polls a little before it sleeps ([`wait`]): on a virtual machine, waking
//! a thread whose CPU has gone idle costs tens of microseconds (a round trip between two idle
//! processes measured 56 µs on this project's 2-core VM, 8 µs while the machine was busy), more
//! than a small session's whole Step. A client that asked again within [`SPIN`] of the last
//! reply is waited for by polling its sockets (`poll` with a zero timeout) for up to [`SPIN`]
//! before the blocking `poll`; a slower client is never polled for. At most one thread fewer
//! than the machine's CPUs polls at once (none on one CPU), so polling cannot starve the trainer
//! or the other clients of every core. The client does the same on its side (`client-py`'s
//! `_shm`).

pub mod layout;
pub mod region;

use std::io::IoSlice;
use std::mem::MaybeUninit;
use std::os::fd::{AsFd, OwnedFd};
use std::sync::Arc;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::{Duration, Instant};

use rustix::event::{PollFd, PollFlags, Timespec};
use rustix::io::Errno;
use rustix::net::{
    AddressFamily, RecvFlags, SendAncillaryBuffer, SendAncillaryMessage, SendFlags, SocketAddrUnix,
    SocketFlags, SocketType, sockopt,
};
use rustix::process::Uid;

use crate::budget::Charge;
use crate::pools::CpuPool;
use crate::service::step_path::StepPath;
use crate::session::{SHM_SECRET_BYTES, SessionError, Store};
use crate::shutdown::Shutdown;

use layout::Layout;
use region::Region;

/// How often an idle client's thread and the acceptor look at the shutdown, and how often a
/// client's thread looks at whether each of its sessions still exists (closed or expired over
/// gRPC).
const POLL: Duration = Duration::from_millis(200);
/// The stack of a client's thread: stepping needs little (the planner included).
const THREAD_STACK: usize = 512 * 1024;
/// Bytes of a session ID in the hello: 32 hex digits.
const ID_BYTES: usize = 32;
/// The hello: `H`, the 32-digit session ID and the session's 32-byte secret.
pub const HELLO_BYTES: usize = 1 + ID_BYTES + SHM_SECRET_BYTES;
/// A client that connects and says nothing for this long is hung up on: it holds a thread, and
/// no slot of `--max-shm-sessions`, until its hello. Clients send the hello right after they
/// connect, so a second is ample; 5 s leave a loaded machine room (it was 10 s, when any local
/// user could hold such threads).
pub const HELLO_TIMEOUT: Duration = Duration::from_secs(5);
/// Most connections (of the server's own user: others are closed before this counts them)
/// waiting for their hello at once. One more is closed at once, unanswered (its client steps
/// over gRPC). Hellos follow their connect at once, so even many clients attaching together
/// wait here for microseconds; the cap keeps a looping or stuck process from holding threads
/// and descriptors without end.
pub const MAX_PENDING_HELLOS: usize = 32;
/// The longest a client's thread polls for its client's next Step before it sleeps in `poll`,
/// and the gap between a reply and the next Step under which it polls at all.
pub const SPIN: Duration = Duration::from_micros(100);

/// Why a client was refused its region.
#[derive(Debug, thiserror::Error)]
pub enum ShmError {
    /// The session's refusal, as gRPC would give it.
    #[error(transparent)]
    Session(#[from] SessionError),
    /// `--max-shm-sessions` are live.
    #[error(
        "the server holds its maximum of {0} shared-memory sessions (--max-shm-sessions); step over gRPC"
    )]
    TooMany(usize),
    /// The hello was not one this server knows (its bytes are not echoed: they may hold a
    /// secret).
    #[error(
        "doorbell: a hello of {0} bytes; this server expects {expected}: `H`, the session ID \
         and the session's shm_secret (a client older than the secret: update it, or step over \
         gRPC)",
        expected = HELLO_BYTES
    )]
    Hello(usize),
    /// A message after the hello that this protocol does not know.
    #[error("doorbell: unexpected message of {len} bytes starting {first:?}")]
    Protocol {
        /// Its length.
        len: usize,
        /// Its first byte.
        first: u8,
    },
    /// The region could not be made.
    #[error("shared memory: {0}")]
    Region(#[from] std::io::Error),
    /// The server is shutting down.
    #[error("the server is shutting down")]
    Stopping,
}

impl ShmError {
    /// The status the refusal is answered with, as gRPC would give it.
    fn status(self) -> tonic::Status {
        match self {
            ShmError::Session(e) => e.into(),
            ShmError::TooMany(_) => tonic::Status::resource_exhausted(self.to_string()),
            ShmError::Hello(_) | ShmError::Protocol { .. } => {
                tonic::Status::invalid_argument(self.to_string())
            }
            ShmError::Region(_) => tonic::Status::internal(self.to_string()),
            ShmError::Stopping => crate::shutdown::unavailable(),
        }
    }

    /// The `E` message of a status: `E`, the gRPC code (u32 LE), the message's length (u32 LE),
    /// the message, and the encoded `google.rpc.Status` details the gRPC status would carry.
    fn encode(s: &tonic::Status) -> Vec<u8> {
        let mut out = vec![b'E'];
        out.extend_from_slice(&(s.code() as i32 as u32).to_le_bytes());
        out.extend_from_slice(&(s.message().len() as u32).to_le_bytes());
        out.extend_from_slice(s.message().as_bytes());
        out.extend_from_slice(s.details());
        out
    }
}

/// What the acceptor and every client thread share.
#[derive(Debug)]
struct Shared {
    /// The sessions.
    store: Store,
    /// Where Steps run (the planner's under a permit of the CPU pool the gRPC path uses) and
    /// where their refusals are counted.
    step: StepPath,
    /// Drives a client thread's wait for a permit of the CPU pool.
    runtime: tokio::runtime::Handle,
    /// Fires when the server drains.
    stopping: Shutdown,
    /// The only user served: the server's effective uid.
    owner: Uid,
    /// `--max-shm-sessions`.
    max: usize,
    /// Live shm sessions.
    live: AtomicUsize,
    /// Connections whose thread waits for their hello now (at most [`MAX_PENDING_HELLOS`]).
    pending: AtomicUsize,
    /// Client threads polling for their client's next Step now, and how many may at once.
    polling: AtomicUsize,
    max_polling: usize,
    /// The thread serving each client process's sessions, by the client's pid.
    clients: Clients,
}

impl Shared {
    /// The `E` message of a refusal, counted in the metrics' error counter as gRPC counts its
    /// refusals.
    fn refusal(&self, e: ShmError) -> Vec<u8> {
        ShmError::encode(&self.step.fail(e.status()))
    }
}

/// A session's slot among the live ones, given back when it ends.
struct Slot(Arc<Shared>);

impl Drop for Slot {
    fn drop(&mut self) {
        self.0.live.fetch_sub(1, Ordering::AcqRel);
    }
}

/// A connection's place among those waiting for their hello, given back when the hello came
/// (or did not, or the thread could not start).
struct Pending(Arc<Shared>);

impl Drop for Pending {
    fn drop(&mut self) {
        self.0.pending.fetch_sub(1, Ordering::AcqRel);
    }
}

/// The doorbell: its name, and the thread that accepts clients on it until the server stops.
#[derive(Debug, Clone)]
pub struct Doorbell {
    /// The abstract socket's name (without the leading NUL), told in CreateSession replies.
    name: Arc<str>,
    /// Shared with the threads.
    shared: Arc<Shared>,
}

impl Doorbell {
    /// Binds a fresh doorbell (a name no other server can hold: pid and 64 random bits) and
    /// starts accepting clients for `store`'s sessions, at most `max` at once, until `stopping`.
    /// Called within the server's tokio runtime, which drives the waits for the CPU pool.
    pub fn start(store: Store, max: usize, stopping: Shutdown) -> std::io::Result<Doorbell> {
        let runtime = tokio::runtime::Handle::try_current().map_err(std::io::Error::other)?;
        let owner = owner(rustix::process::geteuid(), overflow_uid())?;
        let mut random = [0u8; 8];
        {
            use rand::TryRngCore;
            rand::rngs::OsRng
                .try_fill_bytes(&mut random)
                .map_err(std::io::Error::other)?;
        }
        let name: Arc<str> = format!(
            "dinerdash-{}-{:016x}",
            std::process::id(),
            u64::from_le_bytes(random)
        )
        .into();
        let listener = rustix::net::socket_with(
            AddressFamily::UNIX,
            SocketType::SEQPACKET,
            SocketFlags::CLOEXEC,
            None,
        )?;
        rustix::net::bind(
            &listener,
            &SocketAddrUnix::new_abstract_name(name.as_bytes())?,
        )?;
        rustix::net::listen(&listener, 128)?;
        // accept() honours the receive timeout: the acceptor wakes to see the shutdown.
        sockopt::set_socket_timeout(&listener, sockopt::Timeout::Recv, Some(POLL))?;
        let step = StepPath::new(CpuPool::beside_steps(), Arc::clone(store.metrics()));
        let shared = Arc::new(Shared {
            store,
            step,
            runtime,
            stopping,
            owner,
            max,
            live: AtomicUsize::new(0),
            pending: AtomicUsize::new(0),
            polling: AtomicUsize::new(0),
            max_polling: std::thread::available_parallelism().map_or(0, |n| n.get() - 1),
            clients: std::sync::Mutex::default(),
        });
        let acceptor = Arc::clone(&shared);
        std::thread::Builder::new()
            .name("shm-doorbell".into())
            .spawn(move || accept(&listener, &acceptor))?;
        tracing::info!(doorbell = %name, max, "shared-memory data plane ready");
        Ok(Doorbell { name, shared })
    }

    /// The name CreateSession replies carry.
    pub fn name(&self) -> &str {
        &self.name
    }

    /// Live shm sessions.
    pub fn live(&self) -> usize {
        self.shared.live.load(Ordering::Acquire)
    }
}

/// The user whose processes the doorbell serves: this server's, unless it is the uid the
/// kernel reports for a user it cannot map into this user namespace (`kernel.overflowuid`,
/// `nobody`): a peer reported so could then be any process of another user namespace that
/// shares the network namespace, and no peer check would hold.
fn owner(euid: Uid, overflow: u32) -> std::io::Result<Uid> {
    if euid.as_raw() == overflow {
        return Err(std::io::Error::other(format!(
            "this server runs as uid {overflow}, the uid the kernel gives peers it cannot \
             map (kernel.overflowuid), so it could not tell its own user's clients from \
             strangers; run it as another user for shared memory"
        )));
    }
    Ok(euid)
}

/// `kernel.overflowuid` (65534 unless changed, or when `/proc` cannot say).
fn overflow_uid() -> u32 {
    std::fs::read_to_string("/proc/sys/kernel/overflowuid")
        .ok()
        .and_then(|uid| uid.trim().parse().ok())
        .unwrap_or(65534)
}

/// Who is at the other end of a doorbell connection: its credentials when it connected
/// (`SO_PEERCRED`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Peer {
    /// Its user.
    pub uid: u32,
    /// Its process; `None` when it runs in a pid namespace this server cannot see (the kernel
    /// says 0: e.g. a client on the host of a server in a container): it is served, alone (no
    /// thread shared with its other sessions).
    pub pid: Option<i32>,
}

/// The credentials of the peer of `sock`, a socket in non-blocking mode (an `accept` with
/// `NONBLOCK`). Read through tokio's `peer_cred` (on a duplicate of the descriptor, registered
/// with `runtime`'s reactor for the moment), not rustix's `socket_peercred`: rustix's `UCred`
/// holds the pid as a non-zero `Pid`, and the kernel's 0 for a peer in another pid namespace
/// made that undefined behaviour (such a client was closed as "another user").
pub fn peer(sock: &impl AsFd, runtime: &tokio::runtime::Handle) -> std::io::Result<Peer> {
    let _inside = runtime.enter();
    let copy = std::os::unix::net::UnixStream::from(sock.as_fd().try_clone_to_owned()?);
    let cred = tokio::net::UnixStream::from_std(copy)?.peer_cred()?;
    Ok(Peer {
        uid: cred.uid(),
        pid: cred.pid().filter(|&pid| pid > 0),
    })
}

/// Accepts clients until the server stops. A connection of another user, or one past
/// [`MAX_PENDING_HELLOS`], is closed here at once, before any thread or allocation; each other
/// one gets a thread of its own until its hello ([`serve_client`]).
fn accept(listener: &OwnedFd, shared: &Arc<Shared>) {
    while !shared.stopping.is_stopping() {
        let flags = SocketFlags::CLOEXEC | SocketFlags::NONBLOCK; // for `peer`
        let sock = match rustix::net::accept_with(listener, flags) {
            Ok(sock) => sock,
            Err(Errno::AGAIN | Errno::INTR | Errno::CONNABORTED) => continue,
            Err(e) => {
                tracing::warn!(error = %e, "doorbell: accept failed");
                std::thread::sleep(POLL);
                continue;
            }
        };
        let peer = match peer(&sock, &shared.runtime) {
            Ok(peer) if peer.uid == shared.owner.as_raw() => peer,
            Ok(_) => {
                drop(sock);
                tracing::debug!("doorbell: closed a connection of another user");
                continue;
            }
            Err(e) => {
                drop(sock);
                tracing::debug!(error = %e, "doorbell: closed a connection whose peer is unknown");
                continue;
            }
        };
        if shared.pending.fetch_add(1, Ordering::AcqRel) >= MAX_PENDING_HELLOS {
            shared.pending.fetch_sub(1, Ordering::AcqRel);
            drop(sock);
            tracing::debug!(
                max = MAX_PENDING_HELLOS,
                "doorbell: closed a connection: too many wait for their hello"
            );
            continue;
        }
        let pending = Pending(Arc::clone(shared));
        let shared = Arc::clone(shared);
        let spawned = std::thread::Builder::new()
            .name("shm-session".into())
            .stack_size(THREAD_STACK)
            .spawn(move || serve_client(sock, peer.pid, pending, &shared));
        if let Err(e) = spawned {
            tracing::warn!(error = %e, "doorbell: no thread for a client");
        }
    }
}

/// One connection, from its hello until its session is served by its client's thread: this
/// thread becomes that thread when its client process has none yet (or the session is a
/// planner's), and otherwise hands the session over and ends.
fn serve_client(sock: OwnedFd, pid: Option<i32>, pending: Pending, shared: &Arc<Shared>) {
    let setup = (|| -> std::io::Result<()> {
        rustix::io::ioctl_fionbio(&sock, false)?; // the hello is waited for, up to a timeout
        sockopt::set_socket_timeout(&sock, sockopt::Timeout::Recv, Some(POLL))?;
        Ok(())
    })();
    if setup.is_err() {
        return;
    }
    // Room for one byte more than a hello, to tell a longer message from one.
    let mut hello = [0u8; HELLO_BYTES + 1];
    let since = std::time::Instant::now();
    let n = loop {
        match rustix::net::recv(&sock, &mut hello, RecvFlags::empty()) {
            Ok((0, _)) => return, // gone without a word
            Ok((n, _)) => break n,
            Err(Errno::AGAIN | Errno::INTR)
                if !shared.stopping.is_stopping() && since.elapsed() < HELLO_TIMEOUT =>
            {
                continue;
            }
            Err(_) => return,
        }
    };
    drop(pending);
    let accepted = handshake(&sock, &hello[..n], shared);
    hello.fill(0); // the secret stays in `Served::secret` only
    let (id, secret, region, slot, charge, heavy) = match accepted {
        Ok(accepted) => accepted,
        Err(e) => {
            let _ = send(&sock, &shared.refusal(e));
            return;
        }
    };
    let served = Served {
        sock,
        id,
        secret,
        region,
        _slot: slot,
        _charge: charge,
        replied: Instant::now(),
        quick: false,
    };
    // A planner's Steps wait for the CPU pool: such a session gets a thread of its own, so that
    // its waits hold up no other session of its client.
    let joined = match pid {
        Some(pid) if !heavy => Client::join(shared, pid, served),
        _ => Joined::Alone(served),
    };
    match joined {
        Joined::Handed => {}
        Joined::Lead(pid, client, served) => serve(vec![served], Some((pid, client)), shared),
        Joined::Alone(served) => serve(vec![served], None, shared),
    }
}

/// One session being served: its doorbell connection, its region, and the slot and budget it
/// holds until it ends.
struct Served {
    sock: OwnedFd,
    id: String,
    secret: [u8; SHM_SECRET_BYTES],
    region: Region,
    _slot: Slot,
    _charge: Charge,
    /// When the last reply went.
    replied: Instant,
    /// Whether the client asked again within [`SPIN`] of the reply before: then its next Step
    /// is polled for.
    quick: bool,
}

impl Served {
    /// Answers what the client sent (`received`, the `recv` of its socket into `message`): a
    /// Step is stepped and replied to. False when the session ends here (the client went or
    /// spoke out of turn, the session is gone, the server stops).
    fn answer(
        &mut self,
        received: rustix::io::Result<(usize, usize)>,
        message: &[u8],
        actions: &mut Vec<u8>,
        shared: &Shared,
    ) -> bool {
        let n = match received {
            Ok((0, _)) => return false, // the client closed or died
            Ok((n, _)) => n,
            Err(Errno::AGAIN | Errno::INTR) => return true,
            Err(_) => return false,
        };
        self.quick = self.replied.elapsed() < SPIN;
        if n != 1 || message[0] != b'S' {
            let e = ShmError::Protocol {
                len: n,
                first: message[0],
            };
            let _ = send(&self.sock, &shared.refusal(e));
            return false;
        }
        if shared.stopping.is_stopping() {
            let _ = send(&self.sock, &shared.refusal(ShmError::Stopping));
            return false;
        }
        if let Err(e) = self.region.read_actions(actions) {
            let _ = send(&self.sock, &shared.refusal(ShmError::Region(e)));
            return false;
        }
        let stepped = shared.step.run_blocking(
            &shared.runtime,
            shared.store.find_shm(&self.id, &self.secret),
            |s| s.step(actions),
        );
        let sent = match stepped {
            Ok(batch) => match self
                .region
                .write_batch(&batch, shared.stopping.drain_remaining_ms())
            {
                Ok(()) => send(&self.sock, b"K"),
                Err(e) => {
                    let _ = send(&self.sock, &shared.refusal(ShmError::Region(e)));
                    return false;
                }
            },
            Err(status) => {
                let sent = send(&self.sock, &ShmError::encode(&status));
                if status.code() == tonic::Code::NotFound {
                    return false;
                }
                sent
            }
        };
        self.replied = Instant::now();
        sent.is_ok() // not reading its replies, or gone, when not
    }
}

impl Drop for Served {
    fn drop(&mut self) {
        tracing::debug!(session = %self.id, "shared-memory session ended");
    }
}

/// The thread serving one client process's sessions: where the hello threads of its later
/// sessions hand them over.
struct Client {
    /// Sessions handed over, taken at the thread's next turn.
    joining: std::sync::Mutex<Vec<Served>>,
    /// Written when a session is handed over, to wake the thread from `poll`.
    wake: OwnedFd,
}

impl std::fmt::Debug for Client {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Client").finish_non_exhaustive()
    }
}

/// What [`Client::join`] did with a session.
enum Joined {
    /// Handed to the thread already serving its client process.
    Handed,
    /// Its client process has no thread: the caller serves it, as the thread of this client.
    Lead(i32, Arc<Client>, Served),
    /// Not handed over and not registered (no eventfd to wake a thread with): the caller
    /// serves it alone.
    Alone(Served),
}

impl Client {
    /// Hands `served` to the thread serving process `pid`, or registers the caller as that
    /// thread.
    fn join(shared: &Shared, pid: i32, served: Served) -> Joined {
        let mut clients = lock(&shared.clients);
        if let Some(client) = clients.get(&pid) {
            lock(&client.joining).push(served);
            let _ = rustix::io::write(&client.wake, &1u64.to_ne_bytes());
            return Joined::Handed;
        }
        let Ok(wake) = rustix::event::eventfd(
            0,
            rustix::event::EventfdFlags::CLOEXEC | rustix::event::EventfdFlags::NONBLOCK,
        ) else {
            return Joined::Alone(served);
        };
        let client = Arc::new(Client {
            joining: std::sync::Mutex::new(Vec::new()),
            wake,
        });
        clients.insert(pid, Arc::clone(&client));
        Joined::Lead(pid, client, served)
    }

    /// Whether the thread may end: nothing was handed over, and (under the registry's lock)
    /// it is unregistered, so that nothing can be.
    fn leave(shared: &Shared, pid: i32, client: &Arc<Client>) -> bool {
        let mut clients = lock(&shared.clients);
        if !lock(&client.joining).is_empty() {
            return false;
        }
        unregister(&mut clients, pid, client);
        true
    }
}

/// The registry of the threads serving client processes, by pid.
type Clients = std::sync::Mutex<std::collections::HashMap<i32, Arc<Client>>>;

/// Removes `client` from the registry, if it is still the thread registered for `pid`.
fn unregister(
    clients: &mut std::collections::HashMap<i32, Arc<Client>>,
    pid: i32,
    client: &Arc<Client>,
) {
    if clients.get(&pid).is_some_and(|c| Arc::ptr_eq(c, client)) {
        clients.remove(&pid);
    }
}

/// A client's thread's registration, ended however the thread ends: a Step that panicked (a
/// bug) must not leave the process's later sessions handed to a thread that is gone (they would
/// wait for their Step's deadline). Those handed over meanwhile close with the [`Client`].
struct Registered<'a> {
    clients: &'a Clients,
    pid: i32,
    client: Arc<Client>,
}

impl Drop for Registered<'_> {
    fn drop(&mut self) {
        unregister(&mut lock(self.clients), self.pid, &self.client);
    }
}

/// Serves `sessions`, and as the thread of client process `pid` those its hello threads hand
/// over, until none is left or the server stops. Each turn answers every session whose client
/// rang, in order, so that no session of the client waits behind another's second Step.
fn serve(mut sessions: Vec<Served>, client: Option<(i32, Arc<Client>)>, shared: &Shared) {
    let mut actions = Vec::new();
    let mut message = [0u8; 16];
    let mut rang = Vec::new();
    let mut checked = Instant::now();
    let _registered = client.as_ref().map(|(pid, c)| Registered {
        clients: &shared.clients,
        pid: *pid,
        client: Arc::clone(c),
    });
    loop {
        if let Some((_, client)) = &client {
            sessions.append(&mut lock(&client.joining));
        }
        if checked.elapsed() >= POLL {
            // The server stops (a Step rung meanwhile was refused as such), or the session was
            // closed or expired over gRPC: the thread, the region and its budget go now.
            if shared.stopping.is_stopping() {
                sessions.clear();
            } else {
                sessions.retain(|s| shared.store.contains(&s.id));
            }
            checked = Instant::now();
        }
        if sessions.is_empty() {
            match &client {
                Some((pid, c)) if !Client::leave(shared, *pid, c) => continue,
                _ => return,
            }
        }
        let wake = client.as_ref().map(|(_, c)| &c.wake);
        wait(&sessions, wake, shared, &mut rang);
        for (served, rang) in sessions.iter_mut().zip(rang.iter_mut()) {
            if *rang {
                let received = rustix::net::recv(&served.sock, &mut message, RecvFlags::DONTWAIT);
                // From here `rang` says whether the session ends.
                *rang = !served.answer(received, &message, &mut actions, shared);
            }
        }
        let mut ends = rang.iter();
        sessions.retain(|_| !ends.next().copied().unwrap_or(false));
    }
}

/// Sets `rang` to whether each session's client sent something (or hung up). Polls without
/// sleeping for up to [`SPIN`] when one of them asked quickly last time (and fewer than
/// [`Shared::max_polling`] threads poll already), then sleeps in `poll` for up to [`POLL`], or
/// until `wake` says a session was handed over.
fn wait(sessions: &[Served], wake: Option<&OwnedFd>, shared: &Shared, rang: &mut Vec<bool>) {
    let mut fds: Vec<PollFd<'_>> = sessions
        .iter()
        .map(|s| PollFd::new(&s.sock, PollFlags::IN))
        .chain(wake.map(|w| PollFd::new(w, PollFlags::IN)))
        .collect();
    let quick = sessions.iter().any(|s| s.quick);
    let mut ready = false;
    if quick {
        if shared.polling.fetch_add(1, Ordering::AcqRel) < shared.max_polling {
            let since = Instant::now();
            let now = Timespec::default();
            while !ready && since.elapsed() < SPIN {
                ready = rustix::event::poll(&mut fds, Some(&now)).is_ok_and(|n| n > 0);
                std::hint::spin_loop();
            }
        }
        shared.polling.fetch_sub(1, Ordering::AcqRel);
    }
    if !ready {
        let timeout = Timespec::try_from(POLL).ok();
        let _ = rustix::event::poll(&mut fds, timeout.as_ref());
    }
    rang.clear();
    rang.extend(
        fds[..sessions.len()]
            .iter()
            .map(|f| !f.revents().is_empty()),
    );
    if let Some(w) = wake
        && fds.last().is_some_and(|f| !f.revents().is_empty())
    {
        let mut count = [0u8; 8];
        let _ = rustix::io::read(w, &mut count);
    }
}

/// The registry's (or a client's) lock; a thread that panicked holding it left nothing half
/// done (each critical section is one insert, push, take or remove).
fn lock<T>(m: &std::sync::Mutex<T>) -> std::sync::MutexGuard<'_, T> {
    m.lock().unwrap_or_else(std::sync::PoisonError::into_inner)
}

/// A session's hello: its ID and secret.
type Hello = (String, [u8; SHM_SECRET_BYTES]);

/// What a hello accepted: the session ID and secret, the region, the session's slot, the
/// region's charge, and whether the session's Steps need the CPU pool (a planner's).
type Accepted = (String, [u8; SHM_SECRET_BYTES], Region, Slot, Charge, bool);

/// Checks the hello (the peer was checked at accept), makes the region, passes it.
fn handshake(sock: &OwnedFd, hello: &[u8], shared: &Arc<Shared>) -> Result<Accepted, ShmError> {
    let (id, secret) = parse_hello(hello)?;
    if shared.stopping.is_stopping() {
        return Err(ShmError::Stopping);
    }
    let session = shared.store.find_shm(&id, &secret)?;
    let taken = shared.live.fetch_add(1, Ordering::AcqRel);
    let slot = Slot(Arc::clone(shared));
    if taken >= shared.max {
        return Err(ShmError::TooMany(shared.max));
    }
    let layout = Layout::new(session.num_envs());
    let charge = shared
        .store
        .budget()
        .charge_region(session.tenant(), layout.bytes as u64)
        .map_err(SessionError::from)?;
    let region = Region::new(layout)?;
    let mut space = [MaybeUninit::uninit(); rustix::cmsg_space!(ScmRights(1))];
    let mut control = SendAncillaryBuffer::new(&mut space);
    let fds = [region.fd()];
    control.push(SendAncillaryMessage::ScmRights(&fds));
    rustix::net::sendmsg(
        sock,
        &[IoSlice::new(b"R")],
        &mut control,
        SendFlags::NOSIGNAL | SendFlags::DONTWAIT,
    )
    .map_err(std::io::Error::from)?;
    tracing::debug!(session = %id, bytes = region.bytes(), "shared-memory session started");
    let heavy = StepPath::heavy(&session);
    Ok((id, secret, region, slot, charge, heavy))
}

/// The session ID and secret of a hello: `H`, 32 characters, 32 bytes.
fn parse_hello(hello: &[u8]) -> Result<Hello, ShmError> {
    if hello.len() != HELLO_BYTES || hello[0] != b'H' {
        return Err(ShmError::Hello(hello.len()));
    }
    let id = String::from_utf8_lossy(&hello[1..=ID_BYTES]).into_owned();
    let mut secret = [0u8; SHM_SECRET_BYTES];
    secret.copy_from_slice(&hello[1 + ID_BYTES..]);
    Ok((id, secret))
}

/// Sends one message without waiting: a client whose socket is full is not reading its replies.
fn send(sock: &impl AsFd, message: &[u8]) -> rustix::io::Result<usize> {
    rustix::net::send(sock, message, SendFlags::NOSIGNAL | SendFlags::DONTWAIT)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_peer_check_reads_the_connecting_user_and_process() {
        let runtime = tokio::runtime::Builder::new_current_thread()
            .enable_io()
            .build()
            .unwrap();
        let flags = SocketFlags::CLOEXEC | SocketFlags::NONBLOCK;
        let (a, b) =
            rustix::net::socketpair(AddressFamily::UNIX, SocketType::SEQPACKET, flags, None)
                .unwrap();
        let me = Peer {
            uid: rustix::process::geteuid().as_raw(),
            pid: Some(std::process::id() as i32),
        };
        assert_eq!(peer(&a, runtime.handle()).unwrap(), me);
        assert_eq!(peer(&b, runtime.handle()).unwrap(), me);
        // Read on a duplicate: the socket itself is left as it was, usable.
        assert!(rustix::io::ioctl_fionbio(&a, false).is_ok());
        assert_eq!(send(&a, b"S"), Ok(1));
        // Not a socket with a peer: no process (the kernel's 0, as for a peer in another pid
        // namespace, read without fault), and no user (-1).
        let lone =
            rustix::net::socket_with(AddressFamily::UNIX, SocketType::SEQPACKET, flags, None)
                .unwrap();
        let nobody = peer(&lone, runtime.handle()).unwrap();
        assert_eq!(
            nobody,
            Peer {
                uid: u32::MAX,
                pid: None
            }
        );
    }

    #[test]
    fn a_server_running_as_the_overflow_uid_serves_no_one() {
        // Every peer the kernel cannot map reads as that uid: no peer check could hold.
        let e = owner(Uid::from_raw(65534), 65534).unwrap_err();
        assert!(e.to_string().contains("kernel.overflowuid"), "{e}");
        assert_eq!(
            owner(Uid::from_raw(1000), 65534).unwrap(),
            Uid::from_raw(1000)
        );
        assert_eq!(owner(Uid::ROOT, 65534).unwrap(), Uid::ROOT);
    }

    #[test]
    fn a_client_thread_that_panics_is_unregistered_and_only_itself() {
        let client = || {
            let flags = rustix::event::EventfdFlags::CLOEXEC;
            Arc::new(Client {
                joining: std::sync::Mutex::new(Vec::new()),
                wake: rustix::event::eventfd(0, flags).unwrap(),
            })
        };
        let (mine, later, other) = (client(), client(), client());
        let clients = Clients::default();
        lock(&clients).insert(7, Arc::clone(&mine));
        lock(&clients).insert(8, Arc::clone(&other));
        let ended = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
            let _registered = Registered {
                clients: &clients,
                pid: 7,
                client: Arc::clone(&mine),
            };
            panic!("a Step's bug");
        }));
        assert!(ended.is_err());
        assert!(!lock(&clients).contains_key(&7));
        assert!(lock(&clients).contains_key(&8));
        // A thread registered since for the same pid (the first one left) is not removed.
        lock(&clients).insert(7, Arc::clone(&later));
        drop(Registered {
            clients: &clients,
            pid: 7,
            client: mine,
        });
        assert!(
            lock(&clients)
                .get(&7)
                .is_some_and(|c| Arc::ptr_eq(c, &later))
        );
    }

    #[test]
    fn a_hello_is_h_the_id_and_the_secret_and_its_refusal_echoes_no_byte() {
        let id = "0123456789abcdef0123456789abcdef";
        let hello = [b"H".as_slice(), id.as_bytes(), &[7u8; SHM_SECRET_BYTES]].concat();
        let (got, secret) = parse_hello(&hello).unwrap();
        assert_eq!((got.as_str(), secret), (id, [7u8; SHM_SECRET_BYTES]));
        // An old client's hello (no secret), a longer one, another letter: refused by length,
        // their bytes not repeated.
        for bad in [
            &hello[..33],
            &[hello.as_slice(), b"x"].concat(),
            &hello[..0],
        ] {
            let e = parse_hello(bad).err().unwrap();
            let text = format!("{e} {e:?}");
            let text = format!("{text} {:?}", e.status());
            assert!(text.contains("shm_secret"), "{text}");
            assert!(!text.contains(id), "{text}");
        }
        let mut other = hello.clone();
        other[0] = b'S';
        assert!(matches!(parse_hello(&other), Err(ShmError::Hello(65))));
    }
}
