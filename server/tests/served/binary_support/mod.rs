//! Shared by the tests of the real binary: a server process started through `sh -c` (so that a
//! test can set its `ulimit` first), its port read from its first line, killed when dropped.

#![allow(dead_code)]

use std::io::{BufRead as _, BufReader, Read};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use super::grpc_support::{PATIENCE, listening_addr};

/// A server process this test started; killed when dropped, so a failing test stops it too.
pub struct Process {
    child: Child,
    /// Where it serves gRPC, `127.0.0.1:port`.
    pub addr: String,
}

impl Process {
    /// Starts `sh -c "<prefix> exec dinerdash-server --port 0 <args>"` and reads its port.
    pub fn start(prefix: &str, args: &str) -> Process {
        Process::start_exe(env!("CARGO_BIN_EXE_dinerdash-server"), prefix, args)
    }

    /// [`Process::start`] of the binary at `exe` (another build, to compare with).
    pub fn start_exe(exe: &str, prefix: &str, args: &str) -> Process {
        Process::spawn(format!("{prefix} exec '{exe}' --port 0 {args}"))
    }

    /// The server binary at `exe` run by `wrapper`, a command that runs the command line after
    /// it (`unshare --pid --fork --kill-child`, which ends the server when it is killed, or
    /// `setpriv`, which execs it): [`Process::pid`] is then the wrapper's (the server's own
    /// when the wrapper execs it).
    pub fn start_under(wrapper: &str, exe: &str, args: &str) -> Process {
        Process::spawn(format!("exec {wrapper} '{exe}' --port 0 {args}"))
    }

    /// [`Process::start_exe`] with `--probe-port 0`: also the address of its probe listener,
    /// read from its second line (`dinerdash-server probes on ADDR`).
    pub fn start_probed(exe: &str, prefix: &str, args: &str) -> (Process, String) {
        let mut child = child(format!(
            "{prefix} exec '{exe}' --port 0 --probe-port 0 {args}"
        ));
        let mut stdout = BufReader::new(child.stdout.take().expect("stdout piped"));
        let mut line = || {
            let mut line = String::new();
            stdout.read_line(&mut line).unwrap();
            line
        };
        let (first, second) = (line(), line());
        let after = |line: &str, prefix: &str| {
            line.trim()
                .strip_prefix(prefix)
                .unwrap_or_else(|| panic!("unexpected line {line:?}"))
                .to_owned()
        };
        let addr = after(&first, "dinerdash-server listening on ");
        let probe = after(&second, "dinerdash-server probes on ");
        (Process { child, addr }, probe)
    }

    fn spawn(script: String) -> Process {
        let mut child = child(script);
        let addr = listening_addr(&mut child);
        Process { child, addr }
    }

    /// The process ID.
    pub fn pid(&self) -> u32 {
        self.child.id()
    }

    /// How many sockets the process holds open (Linux /proc): its listeners and connections.
    pub fn sockets(&self) -> usize {
        std::fs::read_dir(format!("/proc/{}/fd", self.child.id()))
            .unwrap()
            .filter_map(Result::ok)
            .filter(|fd| {
                std::fs::read_link(fd.path())
                    .is_ok_and(|target| target.to_string_lossy().starts_with("socket:"))
            })
            .count()
    }

    pub fn signal(&self, name: &str) {
        let pid = self.child.id().to_string();
        assert!(
            Command::new("kill")
                .args([name, &pid])
                .status()
                .unwrap()
                .success()
        );
    }

    /// User plus system CPU time so far, in clock ticks (Linux /proc).
    pub fn cpu_ticks(&self) -> u64 {
        let stat = std::fs::read_to_string(format!("/proc/{}/stat", self.child.id())).unwrap();
        // Fields after the command name (which is in parentheses): utime is 14th, stime 15th.
        let rest = &stat[stat.rfind(')').unwrap() + 2..];
        let fields: Vec<&str> = rest.split(' ').collect();
        fields[11].parse::<u64>().unwrap() + fields[12].parse::<u64>().unwrap()
    }

    /// Sends SIGTERM and waits (on a blocking thread) for the process to exit: its status and
    /// stderr.
    pub async fn terminate(self) -> (std::process::ExitStatus, String) {
        self.signal("-TERM");
        tokio::task::spawn_blocking(move || self.wait())
            .await
            .unwrap()
    }

    /// Waits for the process to exit and returns its stderr.
    pub fn wait(mut self) -> (std::process::ExitStatus, String) {
        let started = Instant::now();
        let status = loop {
            if let Some(status) = self.child.try_wait().unwrap() {
                break status;
            }
            assert!(started.elapsed() < PATIENCE, "the server did not exit");
            std::thread::sleep(Duration::from_millis(20));
        };
        let mut stderr = String::new();
        self.child
            .stderr
            .take()
            .unwrap()
            .read_to_string(&mut stderr)
            .unwrap();
        (status, stderr)
    }
}

/// `sh -c script`, its stdout and stderr piped.
fn child(script: String) -> Child {
    Command::new("sh")
        .arg("-c")
        .arg(script)
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .unwrap()
}

impl Drop for Process {
    fn drop(&mut self) {
        let _ = self.child.kill();
        let _ = self.child.wait();
    }
}
