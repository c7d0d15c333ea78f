//! Serving, the command without a subcommand: logging as `--log-format` asks, then
//! [`crate::server::serve`] on a tokio runtime until SIGINT/SIGTERM.

use std::process::ExitCode;

use crate::config::{LogFormat, ServeArgs};
use crate::server;

/// Serves with `args`; failure is logged and printed to stderr.
pub fn execute(args: &ServeArgs) -> ExitCode {
    init_logging(args.log_format);
    let result = super::runtime()
        .map_err(|e| e.to_string())
        .and_then(|rt| rt.block_on(server::serve(args)).map_err(|e| e.to_string()));
    match result {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            tracing::error!("{e}");
            eprintln!("error: {e}");
            ExitCode::FAILURE
        }
    }
}

/// Logs to stderr, filtered by `RUST_LOG` (default `info`), as text or JSON lines.
fn init_logging(format: LogFormat) {
    let filter = tracing_subscriber::EnvFilter::try_from_default_env()
        .unwrap_or_else(|_| tracing_subscriber::EnvFilter::new("info"));
    let builder = tracing_subscriber::fmt()
        .with_env_filter(filter)
        .with_writer(std::io::stderr)
        .with_ansi(std::io::IsTerminal::is_terminal(&std::io::stderr()));
    match format {
        LogFormat::Text => builder.init(),
        LogFormat::Json => builder.json().init(),
    }
}
