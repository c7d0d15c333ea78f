//! The shared-memory data plane end to end: a session created over gRPC, stepped through its
//! region and doorbell, gives exactly the Batches a twin session gives over gRPC; bad actions
//! and unknown sessions are refused with gRPC's code and message; a client that goes ends its
//! session's thread and frees the region's budget.
#![cfg(target_os = "linux")]

mod grpc_support;

use std::io::{IoSlice, IoSliceMut};
use std::mem::MaybeUninit;
use std::os::fd::OwnedFd;
use std::time::{Duration, Instant};

use dinerdash_server::pb;
use dinerdash_server::server::ServerConfig;
use dinerdash_server::shm::layout::{FIELDS, Layout};
use grpc_support::{Actions, PATIENCE, TestServer, create_request, pack, reset, step};
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

/// Connects to `doorbell` and says hello for `session`: the region, or the `E` message.
fn connect(doorbell: &str, session: &str) -> Result<ShmClient, Vec<u8>> {
    let sock = rustix::net::socket_with(
        AddressFamily::UNIX,
        SocketType::SEQPACKET,
        SocketFlags::CLOEXEC,
        None,
    )
    .unwrap();
    let addr = SocketAddrUnix::new_abstract_name(doorbell.as_bytes()).unwrap();
    rustix::net::connect(&sock, &addr).unwrap();
    let hello = [b"H".as_slice(), session.as_bytes()].concat();
    rustix::net::sendmsg(
        &sock,
        &[IoSlice::new(&hello)],
        &mut SendAncillaryBuffer::default(),
        SendFlags::empty(),
    )
    .unwrap();
    let mut reply = [0u8; 4096];
    let mut space = [MaybeUninit::uninit(); rustix::cmsg_space!(ScmRights(1))];
    let mut control = RecvAncillaryBuffer::new(&mut space);
    let got = rustix::net::recvmsg(
        &sock,
        &mut [IoSliceMut::new(&mut reply)],
        &mut control,
        RecvFlags::empty(),
    )
    .unwrap();
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
        let (offset, _) = self.layout.actions();
        rustix::io::pwrite(&self.region, &pack(actions), offset as u64).unwrap();
        rustix::net::send(&self.sock, b"S", SendFlags::empty()).unwrap();
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
        }
        assert!(doorbell.starts_with("dinerdash-"), "{doorbell:?}");
        let (over_shm, over_grpc) = (&ids[0], &ids[1]);
        reset(&mut client, over_shm, None).await;
        reset(&mut client, over_grpc, None).await;
        let shm = tokio::task::block_in_place(|| connect(&doorbell, over_shm)).unwrap();
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
    reset(&mut client, &id, None).await;
    let shm = tokio::task::block_in_place(|| connect(&reply.shm_doorbell, &id)).unwrap();
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
    let e = tokio::task::block_in_place(|| connect(&reply.shm_doorbell, &unknown))
        .err()
        .unwrap();
    assert_eq!(refusal(&e).0, tonic::Code::NotFound as i32);

    // --max-shm-sessions 2: a third region is refused, and given back when a client goes.
    let other = tokio::task::block_in_place(|| connect(&reply.shm_doorbell, &id)).unwrap();
    let e = tokio::task::block_in_place(|| connect(&reply.shm_doorbell, &id))
        .err()
        .unwrap();
    assert_eq!(refusal(&e).0, tonic::Code::ResourceExhausted as i32);
    drop(other);
    let deadline = Instant::now() + PATIENCE;
    loop {
        match tokio::task::block_in_place(|| connect(&reply.shm_doorbell, &id)) {
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
