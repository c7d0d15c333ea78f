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
//! actions into the region and sends `S`; the session's thread copies them out, steps the
//! session exactly as the gRPC Step does (same checks, same errors: `E`, the gRPC code, the
//! message and the encoded `google.rpc.Status` details, counted in the metrics' error counter),
//! writes the reply's arrays into the region and answers `K`. A planner session's Steps wait
//! for a permit of the bounded CPU pool the gRPC path uses ([`crate::service::step_path`]).
//!
//! Why a socket and not a futex or an eventfd: one `recv` wakes the thread and tells it when the
//! client died (the socket closes with the process, `kill -9` included), and the handshake, the
//! descriptor passing and the peer check come with it. Why a std thread per shm session rather
//! than a tokio task: the step is synchronous CPU work of tens of microseconds, a blocked thread
//! wakes within one context switch, and a session's thread can only ever slow its own client.
//! `--max-shm-sessions` bounds the threads and the regions (and [`MAX_PENDING_HELLOS`] the
//! threads still waiting for a hello); the regions count in the memory budget.
//!
//! Why the thread polls a little before it sleeps ([`poll_next`]): on a virtual machine, waking
//! a thread whose CPU has gone idle costs tens of microseconds (a round trip between two idle
//! processes measured 56 µs on this project's 2-core VM, 8 µs while the machine was busy), more
//! than a small session's whole Step. A client that asked again within [`SPIN`] of the last
//! reply is waited for by polling the socket (non-blocking `recv`) for up to [`SPIN`] before the
//! blocking `recv`; a slower client is never polled for. At most one thread fewer than the
//! machine's CPUs polls at once (none on one CPU), so polling cannot starve the trainer or the
//! other sessions of every core. The client does the same on its side (`client-py`'s `_shm`).

pub mod layout;
pub mod region;

use std::io::IoSlice;
use std::mem::MaybeUninit;
use std::os::fd::{AsFd, OwnedFd};
use std::sync::Arc;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::{Duration, Instant};

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

/// How often an idle session's thread and the acceptor look at the shutdown and at whether the
/// session still exists (closed or expired over gRPC).
const POLL: Duration = Duration::from_millis(200);
/// The stack of a session's thread: stepping needs little (the planner included).
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
/// The longest a session's thread polls for its client's next Step before it sleeps in `recv`,
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

/// What the acceptor and every session thread share.
#[derive(Debug)]
struct Shared {
    /// The sessions.
    store: Store,
    /// Where Steps run (the planner's under a permit of the CPU pool the gRPC path uses) and
    /// where their refusals are counted.
    step: StepPath,
    /// Drives a session thread's wait for a permit of the CPU pool.
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
    /// Session threads polling for their client's next Step now, and how many may at once.
    polling: AtomicUsize,
    max_polling: usize,
}

impl Shared {
    /// The `E` message of a refusal, counted in the metrics' error counter as gRPC counts its
    /// refusals.
    fn refusal(&self, e: ShmError) -> Vec<u8> {
        ShmError::encode(&self.step.fail(e.status()))
    }
}

/// A session thread's slot among the live ones, given back when the thread ends.
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
            owner: rustix::process::geteuid(),
            max,
            live: AtomicUsize::new(0),
            pending: AtomicUsize::new(0),
            polling: AtomicUsize::new(0),
            max_polling: std::thread::available_parallelism().map_or(0, |n| n.get() - 1),
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

/// Whether the peer of `sock` runs as `owner`: its credentials when it connected
/// (`SO_PEERCRED`). A peer whose credentials cannot be read is not.
pub fn peer_is(sock: &impl AsFd, owner: Uid) -> bool {
    sockopt::socket_peercred(sock).is_ok_and(|peer| peer.uid == owner)
}

/// Accepts clients until the server stops. A connection of another user, or one past
/// [`MAX_PENDING_HELLOS`], is closed here at once, before any thread or allocation; each other
/// one gets a thread of its own.
fn accept(listener: &OwnedFd, shared: &Arc<Shared>) {
    while !shared.stopping.is_stopping() {
        let sock = match rustix::net::accept_with(listener, SocketFlags::CLOEXEC) {
            Ok(sock) => sock,
            Err(Errno::AGAIN | Errno::INTR | Errno::CONNABORTED) => continue,
            Err(e) => {
                tracing::warn!(error = %e, "doorbell: accept failed");
                std::thread::sleep(POLL);
                continue;
            }
        };
        if !peer_is(&sock, shared.owner) {
            drop(sock);
            tracing::debug!("doorbell: closed a connection of another user");
            continue;
        }
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
            .spawn(move || serve_client(sock, pending, &shared));
        if let Err(e) = spawned {
            tracing::warn!(error = %e, "doorbell: no thread for a client");
        }
    }
}

/// One client, from its hello until it goes, its session goes, or the server stops.
fn serve_client(sock: OwnedFd, pending: Pending, shared: &Arc<Shared>) {
    let setup = (|| -> std::io::Result<()> {
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
    hello.fill(0); // the secret stays in `secret` only
    let (id, secret, mut region, _slot, _charge) = match accepted {
        Ok(accepted) => accepted,
        Err(e) => {
            let _ = send(&sock, &shared.refusal(e));
            return;
        }
    };
    let _span = tracing::debug_span!("shm_session", session = %id).entered();
    let mut message = [0u8; 16];
    let mut actions = Vec::new();
    // When the last reply went, and whether the client asked again within SPIN of the one
    // before: only then is its next Step polled for.
    let mut replied = Instant::now();
    let mut quick = false;
    loop {
        let polled = if quick {
            poll_next(&sock, &mut message, shared)
        } else {
            None
        };
        let received =
            polled.unwrap_or_else(|| rustix::net::recv(&sock, &mut message, RecvFlags::empty()));
        quick = replied.elapsed() < SPIN;
        match received {
            Ok((0, _)) => break, // the client closed or died
            Ok((n, _)) if n == 1 && message[0] == b'S' => {
                if shared.stopping.is_stopping() {
                    let _ = send(&sock, &shared.refusal(ShmError::Stopping));
                    break;
                }
                if let Err(e) = region.read_actions(&mut actions) {
                    let _ = send(&sock, &shared.refusal(ShmError::Region(e)));
                    break;
                }
                let stepped = shared.step.run_blocking(
                    &shared.runtime,
                    shared.store.find_shm(&id, &secret),
                    |s| s.step(&actions),
                );
                let sent = match stepped {
                    Ok(batch) => {
                        match region.write_batch(&batch, shared.stopping.drain_remaining_ms()) {
                            Ok(()) => send(&sock, b"K"),
                            Err(e) => {
                                let _ = send(&sock, &shared.refusal(ShmError::Region(e)));
                                break;
                            }
                        }
                    }
                    Err(status) => {
                        let gone = status.code() == tonic::Code::NotFound;
                        let sent = send(&sock, &ShmError::encode(&status));
                        if gone {
                            break;
                        }
                        sent
                    }
                };
                if sent.is_err() {
                    break; // not reading its replies, or gone
                }
                replied = Instant::now();
            }
            Ok((n, _)) => {
                let e = ShmError::Protocol {
                    len: n,
                    first: message[0],
                };
                let _ = send(&sock, &shared.refusal(e));
                break;
            }
            Err(Errno::AGAIN | Errno::INTR) => {
                if shared.stopping.is_stopping() || !shared.store.contains(&id) {
                    break;
                }
            }
            Err(_) => break,
        }
    }
    tracing::debug!(session = %id, "shared-memory session ended");
}

/// The client's next message if it comes within [`SPIN`], polled for without sleeping; `None`
/// when it did not come (or [`Shared::max_polling`] threads poll already): then `recv` waits.
fn poll_next(
    sock: &OwnedFd,
    message: &mut [u8],
    shared: &Shared,
) -> Option<rustix::io::Result<(usize, usize)>> {
    if shared.polling.fetch_add(1, Ordering::AcqRel) >= shared.max_polling {
        shared.polling.fetch_sub(1, Ordering::AcqRel);
        return None;
    }
    let since = Instant::now();
    let received = loop {
        match rustix::net::recv(sock, &mut *message, RecvFlags::DONTWAIT) {
            Err(Errno::AGAIN | Errno::INTR) if since.elapsed() < SPIN => std::hint::spin_loop(),
            Err(Errno::AGAIN | Errno::INTR) => break None,
            other => break Some(other),
        }
    };
    shared.polling.fetch_sub(1, Ordering::AcqRel);
    received
}

/// A session's hello: its ID and secret.
type Hello = (String, [u8; SHM_SECRET_BYTES]);

/// Checks the hello (the peer was checked at accept), makes the region, passes it: the session
/// ID and secret, the region, the thread's slot and the region's charge.
fn handshake(
    sock: &OwnedFd,
    hello: &[u8],
    shared: &Arc<Shared>,
) -> Result<(String, [u8; SHM_SECRET_BYTES], Region, Slot, Charge), ShmError> {
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
    Ok((id, secret, region, slot, charge))
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
    fn the_peer_check_reads_the_connecting_user() {
        let (a, b) = rustix::net::socketpair(
            AddressFamily::UNIX,
            SocketType::SEQPACKET,
            SocketFlags::CLOEXEC,
            None,
        )
        .unwrap();
        let me = rustix::process::geteuid();
        assert!(peer_is(&a, me) && peer_is(&b, me));
        let other = Uid::from_raw(me.as_raw().wrapping_add(1));
        assert!(!peer_is(&a, other));
        // Not a socket with a peer: not the owner.
        let lone = rustix::net::socket(AddressFamily::UNIX, SocketType::SEQPACKET, None).unwrap();
        assert!(!peer_is(&lone, me));
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
