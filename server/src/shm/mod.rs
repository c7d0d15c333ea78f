//! The same-host data plane: a client on the server's machine, running as the server's user,
//! steps its session through shared memory instead of gRPC (docs/shm.md).
//!
//! The session is created, reset, forked, closed and expired over gRPC as always; only Step
//! moves. CreateSession names the server's *doorbell*, an abstract-namespace Unix socket
//! (`SOCK_SEQPACKET`: no file to leak, reachable only from this host's network namespace). The
//! client connects and sends `H` and its session ID; the server checks that the peer runs as
//! its own user (`SO_PEERCRED`), creates the session's [`region::Region`] (a memfd laid out by
//! [`layout`]) and passes its descriptor back (`SCM_RIGHTS`). From then on each Step is one
//! message each way: the client writes the actions into the region and sends `S`; the session's
//! thread copies them out, steps the session exactly as the gRPC Step does (same checks, same
//! errors: `E`, the gRPC code, the message and the encoded `google.rpc.Status` details), writes
//! the reply's arrays into the region and answers `K`.
//!
//! Why a socket and not a futex or an eventfd: one `recv` wakes the thread and tells it when the
//! client died (the socket closes with the process, `kill -9` included), and the handshake, the
//! descriptor passing and the peer check come with it. Why a std thread per shm session rather
//! than a tokio task: the step is synchronous CPU work of tens of microseconds, a blocked thread
//! wakes within one context switch, and a session's thread can only ever slow its own client.
//! `--max-shm-sessions` bounds the threads and the regions; the regions count in the memory
//! budget.
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

use crate::budget::Charge;
use crate::service::status;
use crate::session::{SessionError, Store};
use crate::shutdown::Shutdown;

use layout::Layout;
use region::Region;

/// How often an idle session's thread and the acceptor look at the shutdown and at whether the
/// session still exists (closed or expired over gRPC).
const POLL: Duration = Duration::from_millis(200);
/// The stack of a session's thread: stepping needs little (the planner included).
const THREAD_STACK: usize = 512 * 1024;
/// The hello: `H` and a 32-digit session ID.
const HELLO_BYTES: usize = 33;
/// A client that connects and says nothing for this long is hung up on: it holds a thread, and
/// no slot of `--max-shm-sessions` until its hello.
const HELLO_TIMEOUT: Duration = Duration::from_secs(10);
/// The longest a session's thread polls for its client's next Step before it sleeps in `recv`,
/// and the gap between a reply and the next Step under which it polls at all.
pub const SPIN: Duration = Duration::from_micros(100);

/// Why a client was refused its region.
#[derive(Debug, thiserror::Error)]
pub enum ShmError {
    /// The session's refusal, as gRPC would give it.
    #[error(transparent)]
    Session(#[from] SessionError),
    /// The peer runs as another user.
    #[error("shared memory serves only the server's own user (uid {server}), not uid {peer}")]
    OtherUser {
        /// The server's effective uid.
        server: u32,
        /// The peer's.
        peer: u32,
    },
    /// `--max-shm-sessions` are live.
    #[error(
        "the server holds its maximum of {0} shared-memory sessions (--max-shm-sessions); step over gRPC"
    )]
    TooMany(usize),
    /// The doorbell message was not one this protocol knows.
    #[error("doorbell: unexpected message {0:?}")]
    Protocol(Vec<u8>),
    /// The region could not be made.
    #[error("shared memory: {0}")]
    Region(#[from] std::io::Error),
    /// The server is shutting down.
    #[error("the server is shutting down")]
    Stopping,
}

impl ShmError {
    /// The `E` message: `E`, the gRPC code (u32 LE), the message's length (u32 LE), the message,
    /// and the encoded `google.rpc.Status` details the gRPC status would carry.
    fn message(self) -> Vec<u8> {
        let s = match self {
            ShmError::Session(e) => status(e),
            ShmError::OtherUser { .. } => tonic::Status::permission_denied(self.to_string()),
            ShmError::TooMany(_) => tonic::Status::resource_exhausted(self.to_string()),
            ShmError::Protocol(_) => tonic::Status::invalid_argument(self.to_string()),
            ShmError::Region(_) => tonic::Status::internal(self.to_string()),
            ShmError::Stopping => crate::shutdown::unavailable(),
        };
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
    /// Fires when the server drains.
    stopping: Shutdown,
    /// `--max-shm-sessions`.
    max: usize,
    /// Live shm sessions.
    live: AtomicUsize,
    /// Session threads polling for their client's next Step now, and how many may at once.
    polling: AtomicUsize,
    max_polling: usize,
}

/// A session thread's slot among the live ones, given back when the thread ends.
struct Slot(Arc<Shared>);

impl Drop for Slot {
    fn drop(&mut self) {
        self.0.live.fetch_sub(1, Ordering::AcqRel);
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
    pub fn start(store: Store, max: usize, stopping: Shutdown) -> std::io::Result<Doorbell> {
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
        let shared = Arc::new(Shared {
            store,
            stopping,
            max,
            live: AtomicUsize::new(0),
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

/// Accepts clients until the server stops; each gets a thread of its own.
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
        let shared = Arc::clone(shared);
        let spawned = std::thread::Builder::new()
            .name("shm-session".into())
            .stack_size(THREAD_STACK)
            .spawn(move || serve_client(sock, &shared));
        if let Err(e) = spawned {
            tracing::warn!(error = %e, "doorbell: no thread for a client");
        }
    }
}

/// One client, from its hello until it goes, its session goes, or the server stops.
fn serve_client(sock: OwnedFd, shared: &Arc<Shared>) {
    let setup = (|| -> std::io::Result<()> {
        sockopt::set_socket_timeout(&sock, sockopt::Timeout::Recv, Some(POLL))?;
        Ok(())
    })();
    if setup.is_err() {
        return;
    }
    let mut hello = [0u8; 64];
    let since = std::time::Instant::now();
    let n = loop {
        match rustix::net::recv(&sock, &mut hello, RecvFlags::empty()) {
            Ok((n, _)) => break n,
            Err(Errno::AGAIN | Errno::INTR)
                if !shared.stopping.is_stopping() && since.elapsed() < HELLO_TIMEOUT =>
            {
                continue;
            }
            Err(_) => return,
        }
    };
    let (id, mut region, _slot, _charge) = match handshake(&sock, &hello[..n], shared) {
        Ok(accepted) => accepted,
        Err(e) => {
            tracing::debug!(error = %e, "doorbell: refused");
            let _ = send(&sock, &e.message());
            return;
        }
    };
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
                    let _ = send(&sock, &ShmError::Stopping.message());
                    break;
                }
                if let Err(e) = region.read_actions(&mut actions) {
                    let _ = send(&sock, &ShmError::Region(e).message());
                    break;
                }
                let stepped = shared.store.find_proven(&id).and_then(|s| s.step(&actions));
                let sent = match stepped {
                    Ok(batch) => {
                        match region.write_batch(&batch, shared.stopping.drain_remaining_ms()) {
                            Ok(()) => send(&sock, b"K"),
                            Err(e) => {
                                let _ = send(&sock, &ShmError::Region(e).message());
                                break;
                            }
                        }
                    }
                    Err(e) => {
                        let gone = matches!(e, SessionError::NotFound(_));
                        let sent = send(&sock, &ShmError::Session(e).message());
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
                let _ = send(&sock, &ShmError::Protocol(message[..n].to_vec()).message());
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

/// Checks the peer and the hello, makes the region, passes it: the session ID, the region, the
/// thread's slot and the region's charge.
fn handshake(
    sock: &OwnedFd,
    hello: &[u8],
    shared: &Arc<Shared>,
) -> Result<(String, Region, Slot, Charge), ShmError> {
    let peer = sockopt::socket_peercred(sock).map_err(std::io::Error::from)?;
    let server = rustix::process::geteuid();
    if peer.uid != server {
        return Err(ShmError::OtherUser {
            server: server.as_raw(),
            peer: peer.uid.as_raw(),
        });
    }
    if hello.len() != HELLO_BYTES || hello[0] != b'H' {
        return Err(ShmError::Protocol(hello.to_vec()));
    }
    if shared.stopping.is_stopping() {
        return Err(ShmError::Stopping);
    }
    let id = String::from_utf8_lossy(&hello[1..]).into_owned();
    let session = shared.store.find_proven(&id)?;
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
    Ok((id, region, slot, charge))
}

/// Sends one message without waiting: a client whose socket is full is not reading its replies.
fn send(sock: &impl AsFd, message: &[u8]) -> rustix::io::Result<usize> {
    rustix::net::send(sock, message, SendFlags::NOSIGNAL | SendFlags::DONTWAIT)
}
