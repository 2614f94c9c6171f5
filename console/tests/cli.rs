//! The `triax-console` binary as an operator starts it.
//!
//! - `help_says_where_the_console_listens`: `--help` states the Zenoh listen default exactly.
//! - `a_named_page_address_and_no_zenoh_listener`: `--listen localhost:0` is resolved and
//!   served, and the process listens on no other TCP port than the page's: no Zenoh endpoint
//!   unless asked (issue 26).
//! - `gateway_keys_that_cannot_work_are_refused_at_start_naming_them`: a `--gateway-key`
//!   without `=`, with a bad key or file, given twice, or a watched building without one.

use std::collections::HashSet;
use std::io::{BufRead, BufReader, Read, Write};
use std::net::TcpStream;
use std::process::{Child, Command, Stdio};
use std::time::Duration;

const BIN: &str = env!("CARGO_BIN_EXE_triax-console");

#[test]
fn help_says_where_the_console_listens() {
    let out = Command::new(BIN).arg("--help").output().unwrap();
    assert!(out.status.success());
    let help = String::from_utf8(out.stdout).unwrap();
    // clap wraps long help: compare with the whitespace folded.
    let help = help.split_whitespace().collect::<Vec<_>>().join(" ");
    assert!(
        help.contains(
            "--zenoh-listen <LISTEN> Zenoh endpoint to listen on, e.g. tcp/127.0.0.1:7448 (repeat \
             or comma-separate). Default: none, the console only connects (--connect, or \
             multicast scouting), unless a --zenoh-config file lists listen endpoints"
        ),
        "{help}"
    );
    assert!(!help.contains("usually none"), "{help}");
    assert!(
        help.contains("HOST:PORT with an IP address or a name (localhost:9760)"),
        "{help}"
    );
}

/// Kills the console when the test ends, however it ends.
struct Running(Child);

impl Drop for Running {
    fn drop(&mut self) {
        let _ = self.0.kill();
        let _ = self.0.wait();
    }
}

/// Inodes of the TCP sockets in LISTEN state on this machine, per port.
fn listening_sockets() -> Vec<(u16, u64)> {
    let mut out = Vec::new();
    for table in ["/proc/net/tcp", "/proc/net/tcp6"] {
        let Ok(text) = std::fs::read_to_string(table) else {
            continue;
        };
        for line in text.lines().skip(1) {
            let f: Vec<&str> = line.split_whitespace().collect();
            // sl local_address rem_address st tx:rx tr:when retrnsmt uid timeout inode
            if f.len() > 9 && f[3] == "0A" {
                let port = f[1].rsplit(':').next().unwrap();
                out.push((
                    u16::from_str_radix(port, 16).unwrap(),
                    f[9].parse().unwrap(),
                ));
            }
        }
    }
    out
}

/// Inodes of the sockets process `pid` holds.
fn sockets_of(pid: u32) -> HashSet<u64> {
    std::fs::read_dir(format!("/proc/{pid}/fd"))
        .unwrap()
        .filter_map(|e| {
            let link = std::fs::read_link(e.ok()?.path()).ok()?;
            let link = link.to_str()?;
            link.strip_prefix("socket:[")?
                .strip_suffix(']')?
                .parse()
                .ok()
        })
        .collect()
}

#[test]
fn a_named_page_address_and_no_zenoh_listener() {
    let child = Command::new(BIN)
        .args([
            "--listen",
            "localhost:0",
            "--no-multicast-scouting",
            "--no-state",
            "--log",
            "warn",
        ])
        .stdout(Stdio::piped())
        .stderr(Stdio::inherit())
        .spawn()
        .unwrap();
    let mut console = Running(child);
    // The address is printed once Zenoh is joined and the page's port bound.
    let mut line = String::new();
    BufReader::new(console.0.stdout.take().unwrap())
        .read_line(&mut line)
        .unwrap();
    let url = line
        .trim()
        .strip_prefix("triax-console: http://")
        .unwrap_or_else(|| panic!("no address printed: {line:?}"))
        .trim_end_matches('/');
    let addr: std::net::SocketAddr = url.parse().unwrap();
    assert!(addr.ip().is_loopback(), "{addr}");

    let mut s = TcpStream::connect(addr).unwrap();
    s.set_read_timeout(Some(Duration::from_secs(60))).unwrap();
    write!(
        s,
        "GET /api/fleet HTTP/1.1\r\nHost: localhost:{}\r\n\r\n",
        addr.port()
    )
    .unwrap();
    let mut answer = String::new();
    s.read_to_string(&mut answer).unwrap();
    assert!(answer.starts_with("HTTP/1.1 200"), "{answer}");

    let mine = sockets_of(console.0.id());
    let listening: Vec<u16> = listening_sockets()
        .into_iter()
        .filter(|(_, inode)| mine.contains(inode))
        .map(|(port, _)| port)
        .collect();
    assert_eq!(
        listening,
        [addr.port()],
        "the console listens on its page's port only, not for Zenoh"
    );
}

/// `triax-console operator add|list|remove` keeps the accounts file: the password from standard
/// input, hashed (Argon2id), the file readable by its owner only; a bad password or name is
/// refused naming what is wrong, and a console refuses an accounts file that does not read,
/// naming its line.
#[test]
fn operators_are_managed_from_the_command_line() {
    use std::os::unix::fs::PermissionsExt;
    let dir = tempfile::tempdir().unwrap();
    let state = dir.path().to_str().unwrap();
    let run = |args: &[&str], stdin: &str| {
        let mut child = Command::new(BIN)
            .args(["--state-dir", state])
            .args(args)
            .stdin(Stdio::piped())
            .stdout(Stdio::piped())
            .stderr(Stdio::piped())
            .spawn()
            .unwrap();
        child
            .stdin
            .take()
            .unwrap()
            .write_all(stdin.as_bytes())
            .unwrap();
        let out = child.wait_with_output().unwrap();
        (
            out.status.success(),
            String::from_utf8_lossy(&out.stdout).into_owned()
                + &String::from_utf8_lossy(&out.stderr),
        )
    };
    let (ok, said) = run(
        &["operator", "add", "alice", "--role", "operate"],
        "correct horse battery\n",
    );
    assert!(ok, "{said}");
    assert!(said.contains("operator alice (operate)"), "{said}");
    let (ok, _) = run(
        &["operator", "add", "bob", "--role", "admin", "--proxy-only"],
        "",
    );
    assert!(ok);
    let file = dir.path().join("operators");
    let text = std::fs::read_to_string(&file).unwrap();
    assert!(text.contains("alice operate $argon2id$v=19$"), "{text}");
    assert!(!text.contains("correct horse"), "the password is not kept");
    assert!(text.contains("bob admin -"), "{text}");
    assert_eq!(
        std::fs::metadata(&file).unwrap().permissions().mode() & 0o777,
        0o600
    );
    let (ok, said) = run(&["operator", "list"], "");
    assert!(ok);
    assert_eq!(said, "alice operate\nbob admin (proxy only)\n");
    let (ok, said) = run(&["operator", "add", "carol", "--role", "view"], "short\n");
    assert!(!ok);
    assert!(said.contains("at least 10 characters"), "{said}");
    let (ok, said) = run(
        &["operator", "add", "c/d", "--role", "view"],
        "long enough pw\n",
    );
    assert!(!ok);
    assert!(said.contains("not '/'"), "{said}");
    let (ok, _) = run(&["operator", "remove", "bob"], "");
    assert!(ok);
    let (ok, said) = run(&["operator", "remove", "bob"], "");
    assert!(!ok && said.contains("no operator \"bob\""), "{said}");
    // A console will not start on an accounts file that does not read.
    std::fs::write(&file, "alice boss -\n").unwrap();
    let (ok, said) = run(&["--listen", "127.0.0.1:0", "--no-multicast-scouting"], "");
    assert!(!ok);
    assert!(
        said.contains("line 1: role \"boss\" is not view, operate or admin"),
        "{said}"
    );
}

/// A console started with `args` that must refuse to run; its standard error.
fn refused(args: &[&str]) -> String {
    let out = Command::new(BIN)
        .args([
            "--no-state",
            "--no-multicast-scouting",
            "--listen",
            "127.0.0.1:0",
        ])
        .args(args)
        .stdin(Stdio::null())
        .output()
        .unwrap();
    assert!(!out.status.success(), "{args:?} was accepted");
    String::from_utf8_lossy(&out.stderr).into_owned()
}

#[test]
fn gateway_keys_that_cannot_work_are_refused_at_start_naming_them() {
    let e = refused(&["--gateway-key", "hq"]);
    assert!(e.contains("--gateway-key \"hq\": not BUILDING=KEY"), "{e}");
    let e = refused(&["--gateway-key", "hq=zz"]);
    assert!(e.contains("--gateway-key.hq"), "{e}");
    let e = refused(&["--gateway-key", "hq=/nonexistent/gw.key.pub"]);
    assert!(
        e.contains("--gateway-key.hq") && e.contains("cannot read"),
        "{e}"
    );
    let public = triax_protocol::signing::LabSigningKey::from_bytes(&[1; 32]).verifying_key();
    let key = triax_protocol::signing::to_hex(public.as_bytes());
    let e = refused(&["--gateway-key", &format!("hq={key},hq={key}")]);
    assert!(e.contains("building hq given twice"), "{e}");
    let e = refused(&[
        "--gateway-key",
        &format!("hq={key}"),
        "--buildings",
        "hq,annex",
    ]);
    assert!(
        e.contains("building annex is watched but no gateway key is given for it"),
        "{e}"
    );
}
