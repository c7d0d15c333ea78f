//! The real binary exposed beyond its machine: a public `--host` without a token, a public
//! `--http-host` without TLS and weak tokens are refused at start with a message saying what to
//! add (before anything is bound); `--insecure` starts it anyway; with a certificate the web
//! endpoint speaks only HTTPS, and answers only to the host names it serves.

use crate::binary_support;
use crate::grpc_support;

use std::path::PathBuf;
use std::process::{Command, Output};
use std::sync::Arc;

use binary_support::Process;
use dinerdash_server::pb::{self, diner_dash_client::DinerDashClient};
use grpc_support::PATIENCE;
use tokio::io::{AsyncReadExt, AsyncWriteExt};
use tokio::net::TcpStream;
use tokio_rustls::TlsConnector;
use tokio_rustls::rustls::pki_types::{CertificateDer, ServerName, pem::PemObject};
use tokio_rustls::rustls::{self, RootCertStore};

/// The token of these tests: 16 characters or more, no `#`.
const TOKEN: &str = "expose-test-token-0123456789";

/// Runs the binary with `args` and `env` (and no token from this process's environment) until
/// it exits; it must exit on its own, as a refused start does.
async fn refused_start(args: &[&str], env: &[(&str, &str)]) -> Output {
    let exe = env!("CARGO_BIN_EXE_dinerdash-server");
    let mut command = Command::new(exe);
    command.args(args).env_remove("DINERDASH_AUTH_TOKEN");
    for (name, value) in env {
        command.env(name, value);
    }
    let output = tokio::task::spawn_blocking(move || command.output().unwrap())
        .await
        .unwrap();
    assert!(
        !output.status.success(),
        "started: {}",
        String::from_utf8_lossy(&output.stdout)
    );
    // Refused before binding: it never said it listens.
    assert!(output.stdout.is_empty(), "{output:?}");
    output
}

fn stderr(output: &Output) -> String {
    String::from_utf8_lossy(&output.stderr).into_owned()
}

#[tokio::test]
async fn a_public_host_without_a_token_is_refused_and_insecure_starts_it() {
    let refused = refused_start(&["--host", "0.0.0.0", "--port", "0"], &[]).await;
    let message = stderr(&refused);
    for hint in [
        "--host 0.0.0.0",
        "DINERDASH_AUTH_TOKEN",
        "openssl rand -hex 32",
        "--auth-tokens-file",
        "--insecure",
    ] {
        assert!(message.contains(hint), "no {hint:?} in: {message}");
    }

    // Said explicitly, it starts (on every address, so only for a moment), with a warning.
    let server = Process::start(
        "unset DINERDASH_AUTH_TOKEN;",
        "--host 0.0.0.0 --insecure --drain-timeout 0 --max-shm-sessions 0",
    );
    assert!(server.addr.starts_with("0.0.0.0:"), "{}", server.addr);
    let (status, stderr) = server.terminate().await;
    assert_eq!(status.code(), Some(0), "{stderr}");
    assert!(stderr.contains("--insecure: starting anyway"), "{stderr}");
}

#[tokio::test]
async fn public_pages_need_tls_and_weak_tokens_are_refused() {
    let token = [("DINERDASH_AUTH_TOKEN", TOKEN)];
    let http = ["--port", "0", "--http-port", "0", "--http-host", "0.0.0.0"];
    let message = stderr(&refused_start(&http, &token).await);
    assert!(message.contains("--tls-cert"), "{message}");
    assert!(message.contains("--insecure"), "{message}");

    for (weak, why) in [("s3cret", "fewer than 16"), ("0123456789#abcdefgh", "`#`")] {
        let by_env = refused_start(&["--port", "0"], &[("DINERDASH_AUTH_TOKEN", weak)]).await;
        let by_flag = refused_start(&["--port", "0", "--auth-token", weak], &[]).await;
        for output in [by_env, by_flag] {
            let message = stderr(&output);
            assert!(message.contains(why), "{message}");
            assert!(!message.contains(weak), "the token is repeated: {message}");
        }
    }

    let dir = scratch("tenants");
    let file = dir.join("tenants");
    std::fs::write(&file, "team-a team-a-token-aaaa\nteam-b short\n").unwrap();
    let path = file.to_str().unwrap();
    let message = stderr(&refused_start(&["--port", "0", "--auth-tokens-file", path], &[]).await);
    assert!(message.contains("line 2: tenant \"team-b\""), "{message}");
    assert!(
        !message.contains("short\n") && !message.contains("aaaa"),
        "{message}"
    );
    std::fs::remove_dir_all(&dir).unwrap();
}

/// A fresh directory for this test's files.
fn scratch(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("dinerdash-expose-{name}-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// Sends `head` over `stream` and reads the whole reply.
async fn exchange<S>(mut stream: S, head: &str) -> String
where
    S: tokio::io::AsyncRead + tokio::io::AsyncWrite + Unpin,
{
    stream.write_all(head.as_bytes()).await.unwrap();
    let mut reply = Vec::new();
    // A server that hangs up without a TLS close_notify is an error here, after the reply.
    let _ = tokio::time::timeout(PATIENCE, stream.read_to_end(&mut reply))
        .await
        .unwrap();
    String::from_utf8_lossy(&reply).into_owned()
}

#[tokio::test]
async fn the_web_endpoint_serves_tls_with_the_grpc_certificate_and_checks_the_host() {
    let names = vec!["localhost".to_owned(), "dinerdash.test".to_owned()];
    let made = rcgen::generate_simple_self_signed(names).unwrap();
    let cert_pem = made.cert.pem();
    let dir = scratch("tls");
    let (cert, key) = (dir.join("cert.pem"), dir.join("key.pem"));
    std::fs::write(&cert, &cert_pem).unwrap();
    std::fs::write(&key, made.signing_key.serialize_pem()).unwrap();
    let server = Process::start(
        &format!("export DINERDASH_AUTH_TOKEN={TOKEN};"),
        &format!(
            "--tls-cert '{}' --tls-key '{}' --http-port 0 --http-allowed-host Pages.Example.org \
             --max-shm-sessions 0",
            cert.display(),
            key.display()
        ),
    );

    // Where the pages are: ServerInfo, over gRPC with TLS and the token.
    let port = server.addr.rsplit(':').next().unwrap();
    let channel = grpc_support::tls_channel(format!("https://localhost:{port}"), &cert_pem).await;
    let bearer: tonic::metadata::MetadataValue<_> = format!("Bearer {TOKEN}").parse().unwrap();
    let mut client = DinerDashClient::with_interceptor(channel, move |mut r: tonic::Request<()>| {
        r.metadata_mut().insert("authorization", bearer.clone());
        Ok(r)
    });
    let info = client
        .server_info(pb::ServerInfoRequest {})
        .await
        .unwrap()
        .into_inner();
    let pages = format!("127.0.0.1:{}", info.http_port);

    let mut roots = RootCertStore::empty();
    for cert in CertificateDer::pem_slice_iter(cert_pem.as_bytes()) {
        roots.add(cert.unwrap()).unwrap();
    }
    let config = rustls::ClientConfig::builder_with_provider(Arc::new(
        rustls::crypto::ring::default_provider(),
    ))
    .with_safe_default_protocol_versions()
    .unwrap()
    .with_root_certificates(roots)
    .with_no_client_auth();
    let connector = TlsConnector::from(Arc::new(config));
    let https = |host: &'static str, token: Option<&'static str>| {
        let (connector, pages) = (connector.clone(), pages.clone());
        async move {
            let tcp = TcpStream::connect(&pages).await.unwrap();
            let name = ServerName::try_from("localhost").unwrap();
            let tls = connector.connect(name, tcp).await.unwrap();
            let auth = token.map_or(String::new(), |t| format!("Authorization: Bearer {t}\r\n"));
            exchange(
                tls,
                &format!("GET /api/sessions HTTP/1.1\r\nHost: {host}\r\n{auth}\r\n"),
            )
            .await
        }
    };
    // Over TLS, with the token: served, for every name the endpoint answers to.
    for host in [
        "localhost",
        "127.0.0.1:1",
        "dinerdash.test",
        "pages.example.org:443",
    ] {
        let reply = https(host, Some(TOKEN)).await;
        assert!(reply.starts_with("HTTP/1.1 200 OK"), "{host}: {reply}");
        assert!(reply.contains("\"sessions\""), "{reply}");
    }
    // Without it: asked for one.
    let reply = https("localhost", None).await;
    assert!(reply.starts_with("HTTP/1.1 401"), "{reply}");
    // A name the endpoint does not serve (a DNS name rebound to it): refused before routing.
    let reply = https("evil.example.com:8080", Some(TOKEN)).await;
    assert!(reply.starts_with("HTTP/1.1 421"), "{reply}");
    assert!(reply.contains("--http-allowed-host"), "{reply}");
    // Plain HTTP gets no HTTP answer at all.
    let plain = exchange(
        TcpStream::connect(&pages).await.unwrap(),
        &format!(
            "GET /api/sessions HTTP/1.1\r\nHost: localhost\r\nAuthorization: Bearer {TOKEN}\r\n\r\n"
        ),
    )
    .await;
    assert!(!plain.contains("HTTP/1.1"), "{plain:?}");
    assert!(!plain.contains("sessions"), "{plain:?}");

    let (status, _) = server.terminate().await;
    assert_eq!(status.code(), Some(0));
    std::fs::remove_dir_all(&dir).unwrap();
}
