//! Restore tried against the real binary with the worst snapshot (issue 46): one of environments
//! never reset, the smallest on the wire for what it decodes to (its environments take 11x its
//! bytes). The server's peak RSS (`VmHWM`) rises by no more than what the Restore is charged
//! before anything is decoded: its intake charge ([`bounds`]' expansion times its bytes) and the
//! session's charge for the environments its header counts ([`session_bytes`]). A tenant whose share of environments the snapshot's count passes is refused
//! `RESOURCE_EXHAUSTED` from the snapshot's header, before any environment is decoded: the peak
//! then rises by no more than the message and its copy.
//!
//! `DINERDASH_SERVER_EXE=/path/to/dinerdash-server` runs it against another build (the binary
//! before the fix decodes first: the refused Restore raised the peak by its whole session).

use crate::binary_support;

use binary_support::Process;
use dinerdash_server::codec::intake::bounds;
use dinerdash_server::pb::{self, diner_dash_client::DinerDashClient};
use dinerdash_server::session::session_bytes;
use tonic::transport::Channel;
use tonic::{Code, Request};

/// The most environments a session may have by default: the largest snapshot.
const ENVS: u32 = 16_384;
/// The tenant whose share holds the snapshot.
const TOKEN_BIG: &str = "tenant-big-token-Rk3Nw8Qd2Vx6";
/// The tenant whose share is one environment short of it.
const TOKEN_SMALL: &str = "tenant-small-token-Hp5Gz1Lm7Tc4";

/// The server's peak RSS so far (Linux `VmHWM`), in bytes.
fn peak_rss(pid: u32) -> u64 {
    let status = std::fs::read_to_string(format!("/proc/{pid}/status")).unwrap();
    let line = status.lines().find(|l| l.starts_with("VmHWM:")).unwrap();
    let kib: u64 = line.split_whitespace().nth(1).unwrap().parse().unwrap();
    kib * 1024
}

/// The binary under test (`DINERDASH_SERVER_EXE`, else this build's) started with `args`.
fn start(args: &str) -> Process {
    // Warnings only: nobody reads the server's stderr until it exits.
    match std::env::var("DINERDASH_SERVER_EXE") {
        Ok(exe) => Process::start_exe(&exe, "RUST_LOG=warn", args),
        Err(_) => Process::start("RUST_LOG=warn", args),
    }
}

async fn client(server: &Process) -> DinerDashClient<Channel> {
    DinerDashClient::connect(format!("http://{}", server.addr))
        .await
        .unwrap()
        .max_decoding_message_size(64 << 20)
        .max_encoding_message_size(64 << 20)
}

/// A snapshot of a session of `n` environments never reset.
async fn never_reset_snapshot(c: &mut DinerDashClient<Channel>, n: u32) -> Vec<u8> {
    let created = c
        .create_session(pb::CreateSessionRequest {
            num_envs: n,
            ..Default::default()
        })
        .await
        .unwrap()
        .into_inner();
    let snapshot = c
        .snapshot(pb::SnapshotRequest {
            session_id: created.session_id.clone(),
            ..Default::default()
        })
        .await
        .unwrap()
        .into_inner()
        .snapshot;
    let close = pb::CloseSessionRequest {
        session_id: created.session_id,
    };
    c.close_session(close).await.unwrap();
    snapshot
}

/// A Restore of `snapshot` by `token`'s tenant.
async fn restore(
    c: &mut DinerDashClient<Channel>,
    token: &str,
    snapshot: Vec<u8>,
) -> Result<pb::CreateSessionResponse, tonic::Status> {
    let mut request = Request::new(pb::RestoreRequest { snapshot });
    let value = format!("Bearer {token}").parse().unwrap();
    request.metadata_mut().insert("authorization", value);
    c.restore(request).await.map(|r| r.into_inner())
}

#[tokio::test]
async fn the_worst_snapshot_stays_within_its_charge_and_over_a_share_is_refused_undecoded() {
    // The snapshots, made by a server of their own (its peak is not the one measured).
    let maker = start("");
    let mut c = client(&maker).await;
    let worst = never_reset_snapshot(&mut c, ENVS).await;
    let small = never_reset_snapshot(&mut c, 1).await;
    drop(maker);

    let dir = std::env::temp_dir().join(format!("dinerdash-restore-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let file = dir.join("tenants");
    let short = ENVS - 1;
    std::fs::write(
        &file,
        format!("big {TOKEN_BIG}\nsmall {TOKEN_SMALL} envs={short}\n"),
    )
    .unwrap();
    let server = start(&format!("--auth-tokens-file '{}'", file.display()));
    let mut c = client(&server).await;
    // Both tenants' Restore path once (threads, buffers), so that the peak measured is the
    // snapshot's.
    for token in [TOKEN_BIG, TOKEN_SMALL] {
        restore(&mut c, token, small.clone()).await.unwrap();
    }
    let bytes = worst.len() as u64;
    let mib = |b: u64| b as f64 / f64::from(1 << 20);

    // Within the big tenant's share: restored, the peak within the intake charge.
    // What the Restore is charged before decoding: its message (intake) and the session it
    // makes (the memory budget, from the header's count).
    let intake = bounds("/dinerdash.v1.DinerDash/Restore").expansion * bytes;
    let charge = intake + session_bytes(ENVS as usize);
    let before = peak_rss(server.pid());
    let restored = restore(&mut c, TOKEN_BIG, worst.clone()).await.unwrap();
    let rise = peak_rss(server.pid()).saturating_sub(before);
    assert_eq!(restored.spec.unwrap().num_envs, ENVS);
    // Over the small tenant's share: refused from the header, nothing decoded (the session
    // restored above holds its memory: a decode would need as much again).
    let before = peak_rss(server.pid());
    let refused = restore(&mut c, TOKEN_SMALL, worst).await.unwrap_err();
    let refused_rise = peak_rss(server.pid()).saturating_sub(before);
    assert_eq!(refused.code(), Code::ResourceExhausted, "{refused:?}");
    assert!(
        refused.message().contains(&format!("may hold {short}")),
        "{refused:?}"
    );

    eprintln!(
        "never-reset snapshot of {ENVS} environments: {:.1} MiB; Restore: peak +{:.1} MiB for a \
         charge of {:.1} MiB (intake {:.1} MiB, the session {:.1} MiB); refused over the share: \
         peak +{:.1} MiB",
        mib(bytes),
        mib(rise),
        mib(charge),
        mib(intake),
        mib(charge - intake),
        mib(refused_rise)
    );
    assert!(
        refused_rise <= 3 * bytes,
        "the refused Restore raised the peak {:.1} MiB: its environments were decoded",
        mib(refused_rise)
    );
    assert!(
        rise <= charge,
        "the peak rose {:.1} MiB for a charge of {:.1} MiB",
        mib(rise),
        mib(charge)
    );
    drop(server);
    std::fs::remove_dir_all(&dir).unwrap();
}
