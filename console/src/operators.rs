//! Operators with identities: local accounts with Argon2id password hashes, their roles, the
//! sessions of those logged in, and the site's reverse-proxy identity when one is configured.
//!
//! The accounts file (`operators` in the state directory, or `--operators-file`) holds one
//! account a line, `NAME ROLE HASH`: a name of 1 to 64 letters, digits and `._@-`, a role
//! (`view`, `operate`, `admin`) and the password's Argon2id hash in the PHC string format
//! (`$argon2id$v=19$m=19456,t=2,p=1$<salt>$<hash>`), or `-` for an account that only a
//! reverse proxy can name (no password). `#` starts a comment. `triax-console operator add`
//! writes it; the console reads it at start and again whenever its modification time changes,
//! so that a removed account or a changed role holds at the next request.
//!
//! A session is a random 256-bit token in an `HttpOnly`, `SameSite=Strict` cookie: no script
//! can read it and no other site's page can make the browser send it. Sessions live in memory
//! (a restart logs everyone out), at most [`MAX_SESSIONS`], each for [`SESSION_LIFETIME`].

use std::collections::HashMap;
use std::path::{Path, PathBuf};
use std::sync::Mutex;
use std::time::{Duration, Instant, SystemTime};

use argon2::password_hash::{PasswordHash, PasswordHasher, PasswordVerifier, SaltString};
use argon2::Argon2;
use rand::RngCore;
use serde::Serialize;

/// The accounts file's name in the state directory.
pub const FILE_NAME: &str = "operators";
/// Longest account name, in characters.
pub const MAX_NAME_CHARS: usize = 64;
/// Shortest password accepted by `operator add`.
pub const MIN_PASSWORD_CHARS: usize = 10;
/// Longest password checked (Argon2 takes any length; a bound keeps a login's cost bounded).
pub const MAX_PASSWORD_BYTES: usize = 1024;
/// Sessions kept at once; the oldest goes first.
pub const MAX_SESSIONS: usize = 1000;
/// How long a login lasts.
pub const SESSION_LIFETIME: Duration = Duration::from_secs(12 * 3600);
/// The session cookie's name.
pub const COOKIE: &str = "triax_session";

/// What an operator may do; each role may do what the ones before it may.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Role {
    /// Sees everything the console shows.
    View,
    /// Also acknowledges, silences and lifts silences, and annotates.
    Operate,
    /// Also clears a field-health latch and removes anyone's annotation.
    Admin,
}

impl Role {
    pub fn parse(s: &str) -> Option<Role> {
        match s {
            "view" => Some(Role::View),
            "operate" => Some(Role::Operate),
            "admin" => Some(Role::Admin),
            _ => None,
        }
    }

    pub fn name(self) -> &'static str {
        match self {
            Role::View => "view",
            Role::Operate => "operate",
            Role::Admin => "admin",
        }
    }
}

/// One account.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Account {
    pub name: String,
    pub role: Role,
    /// The PHC string of the password's hash; none: named by the reverse proxy only.
    pub hash: Option<String>,
}

/// A bad accounts file or account: what and where.
#[derive(Debug, thiserror::Error)]
pub enum OperatorError {
    #[error("operators file {path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("operators file {path}, line {line}: {reason}")]
    Line {
        path: PathBuf,
        line: usize,
        reason: String,
    },
    #[error("{0}")]
    Invalid(String),
}

/// Whether `name` may be an account's name.
pub fn check_name(name: &str) -> Result<(), String> {
    if name.is_empty() || name.chars().count() > MAX_NAME_CHARS {
        return Err(format!(
            "an operator's name is 1 to {MAX_NAME_CHARS} characters, not {}",
            name.chars().count()
        ));
    }
    if let Some(c) = name
        .chars()
        .find(|c| !(c.is_ascii_alphanumeric() || "._@-".contains(*c)))
    {
        return Err(format!(
            "an operator's name is letters, digits and . _ @ -, not {c:?}"
        ));
    }
    Ok(())
}

/// The Argon2id hash of `password` with a fresh random salt, as a PHC string.
pub fn hash_password(password: &str) -> Result<String, OperatorError> {
    if password.chars().count() < MIN_PASSWORD_CHARS {
        return Err(OperatorError::Invalid(format!(
            "a password is at least {MIN_PASSWORD_CHARS} characters"
        )));
    }
    if password.len() > MAX_PASSWORD_BYTES {
        return Err(OperatorError::Invalid(format!(
            "a password is at most {MAX_PASSWORD_BYTES} bytes"
        )));
    }
    let salt = SaltString::generate(&mut rand::rngs::OsRng);
    Argon2::default()
        .hash_password(password.as_bytes(), &salt)
        .map(|h| h.to_string())
        .map_err(|e| OperatorError::Invalid(format!("hashing the password: {e}")))
}

/// Reads an accounts file; a missing file is no accounts.
pub fn read_accounts(path: &Path) -> Result<Vec<Account>, OperatorError> {
    let text = match std::fs::read_to_string(path) {
        Ok(t) => t,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Vec::new()),
        Err(source) => {
            return Err(OperatorError::Io {
                path: path.to_owned(),
                source,
            })
        }
    };
    parse_accounts(path, &text)
}

fn parse_accounts(path: &Path, text: &str) -> Result<Vec<Account>, OperatorError> {
    let mut out: Vec<Account> = Vec::new();
    for (i, line) in text.lines().enumerate() {
        let bad = |reason: String| OperatorError::Line {
            path: path.to_owned(),
            line: i + 1,
            reason,
        };
        let line = line.trim();
        if line.is_empty() || line.starts_with('#') {
            continue;
        }
        let f: Vec<&str> = line.split_whitespace().collect();
        let [name, role, hash] = f[..] else {
            return Err(bad(format!(
                "expected NAME ROLE HASH, found {} fields",
                f.len()
            )));
        };
        check_name(name).map_err(bad)?;
        let role = Role::parse(role)
            .ok_or_else(|| bad(format!("role {role:?} is not view, operate or admin")))?;
        let hash = if hash == "-" {
            None
        } else {
            let parsed = PasswordHash::new(hash)
                .map_err(|e| bad(format!("the hash is not a PHC string: {e}")))?;
            if parsed.algorithm.as_str() != "argon2id" {
                return Err(bad(format!(
                    "the hash is {}, not argon2id",
                    parsed.algorithm
                )));
            }
            Some(hash.to_owned())
        };
        if out.iter().any(|a| a.name == name) {
            return Err(bad(format!("operator {name:?} is listed twice")));
        }
        out.push(Account {
            name: name.to_owned(),
            role,
            hash,
        });
    }
    Ok(out)
}

/// Writes `accounts` to `path` (a temporary file renamed over it), readable by its owner only.
pub fn write_accounts(path: &Path, accounts: &[Account]) -> Result<(), OperatorError> {
    use std::io::Write;
    let io = |source| OperatorError::Io {
        path: path.to_owned(),
        source,
    };
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).map_err(io)?;
    }
    let mut text = String::from(
        "# triax-console operators: NAME ROLE HASH (Argon2id, PHC string; - for a proxy-named account)\n",
    );
    for a in accounts {
        text.push_str(&format!(
            "{} {} {}\n",
            a.name,
            a.role.name(),
            a.hash.as_deref().unwrap_or("-")
        ));
    }
    let tmp = path.with_extension("tmp");
    let mut f = {
        let mut o = std::fs::OpenOptions::new();
        o.write(true).create(true).truncate(true);
        #[cfg(unix)]
        {
            use std::os::unix::fs::OpenOptionsExt;
            o.mode(0o600);
        }
        o.open(&tmp).map_err(io)?
    };
    f.write_all(text.as_bytes()).map_err(io)?;
    f.sync_all().map_err(io)?;
    drop(f);
    std::fs::rename(&tmp, path).map_err(io)
}

/// Who made a request, as the console knows them.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct Operator {
    pub name: String,
    pub role: Role,
    /// `password` (a session of the console's own login) or `proxy` (the identity header).
    pub via: &'static str,
}

#[derive(Debug)]
struct Session {
    name: String,
    created: Instant,
}

#[derive(Debug)]
struct Loaded {
    accounts: Vec<Account>,
    modified: Option<SystemTime>,
    /// Why the file could not be read again, if it could not (the accounts before stay).
    error: Option<String>,
}

/// The accounts and the sessions. Shared by every connection.
#[derive(Debug)]
pub struct Operators {
    path: Option<PathBuf>,
    /// The request header that names the operator (a reverse proxy's), if trusted.
    identity_header: Option<String>,
    loaded: Mutex<Loaded>,
    sessions: Mutex<HashMap<String, Session>>,
    /// A hash to check a password against when the name is unknown, so that the answer takes
    /// as long for a name that exists as for one that does not.
    decoy: String,
}

/// The outcome of a login.
#[derive(Debug, PartialEq, Eq)]
pub enum Login {
    /// The token of the new session, and who.
    Ok(String, Operator),
    /// Unknown name, wrong password, or an account without a password.
    Refused,
}

impl Operators {
    /// The accounts of `path` (none: no accounts), and the trusted identity header.
    pub fn open(
        path: Option<PathBuf>,
        identity_header: Option<String>,
    ) -> Result<Operators, OperatorError> {
        let (accounts, modified) = match &path {
            Some(p) => (read_accounts(p)?, modified(p)),
            None => (Vec::new(), None),
        };
        // Parameters as the real hashes', so that a decoy check costs the same.
        let salt = SaltString::generate(&mut rand::rngs::OsRng);
        let decoy = Argon2::default()
            .hash_password(b"no such operator", &salt)
            .map(|h| h.to_string())
            .map_err(|e| OperatorError::Invalid(format!("hashing: {e}")))?;
        Ok(Operators {
            path,
            identity_header: identity_header.map(|h| h.to_ascii_lowercase()),
            loaded: Mutex::new(Loaded {
                accounts,
                modified,
                error: None,
            }),
            sessions: Mutex::new(HashMap::new()),
            decoy,
        })
    }

    /// No accounts and no identity header: the console is read-only and open on loopback.
    pub fn none() -> Operators {
        Operators {
            path: None,
            identity_header: None,
            loaded: Mutex::new(Loaded {
                accounts: Vec::new(),
                modified: None,
                error: None,
            }),
            sessions: Mutex::new(HashMap::new()),
            decoy: String::new(),
        }
    }

    /// Whether every page and route needs a logged-in operator: once any account exists, or a
    /// reverse proxy names operators.
    pub fn login_required(&self) -> bool {
        self.identity_header.is_some() || !self.accounts().is_empty()
    }

    pub fn identity_header(&self) -> Option<&str> {
        self.identity_header.as_deref()
    }

    pub fn path(&self) -> Option<&Path> {
        self.path.as_deref()
    }

    /// The accounts now, read again if the file changed.
    pub fn accounts(&self) -> Vec<Account> {
        let mut l = self.loaded.lock().unwrap_or_else(|p| p.into_inner());
        if let Some(p) = &self.path {
            let m = modified(p);
            if m != l.modified {
                match read_accounts(p) {
                    Ok(a) => {
                        l.accounts = a;
                        l.error = None;
                    }
                    Err(e) => {
                        tracing::warn!(cause = %e, "operators file not read again; keeping the accounts before");
                        l.error = Some(e.to_string());
                    }
                }
                l.modified = m;
            }
        }
        l.accounts.clone()
    }

    fn account(&self, name: &str) -> Option<Account> {
        self.accounts().into_iter().find(|a| a.name == name)
    }

    /// Checks a name and password; on success opens a session.
    pub fn login(&self, name: &str, password: &str) -> Login {
        let account = self.account(name);
        let hash = account
            .as_ref()
            .and_then(|a| a.hash.clone())
            .unwrap_or_else(|| self.decoy.clone());
        let ok = password.len() <= MAX_PASSWORD_BYTES
            && PasswordHash::new(&hash).is_ok_and(|h| {
                Argon2::default()
                    .verify_password(password.as_bytes(), &h)
                    .is_ok()
            });
        let Some(account) = account.filter(|a| ok && a.hash.is_some()) else {
            return Login::Refused;
        };
        let mut bytes = [0u8; 32];
        rand::rngs::OsRng.fill_bytes(&mut bytes);
        let token: String = bytes.iter().map(|b| format!("{b:02x}")).collect();
        let mut s = self.sessions.lock().unwrap_or_else(|p| p.into_inner());
        s.retain(|_, v| v.created.elapsed() < SESSION_LIFETIME);
        while s.len() >= MAX_SESSIONS {
            let Some(oldest) = s
                .iter()
                .min_by_key(|(_, v)| v.created)
                .map(|(k, _)| k.clone())
            else {
                break;
            };
            s.remove(&oldest);
        }
        s.insert(
            token.clone(),
            Session {
                name: account.name.clone(),
                created: Instant::now(),
            },
        );
        Login::Ok(
            token,
            Operator {
                name: account.name,
                role: account.role,
                via: "password",
            },
        )
    }

    /// Ends the session of `token`, if any.
    pub fn logout(&self, token: &str) {
        self.sessions
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .remove(token);
    }

    /// Who a request comes from: its session cookie's operator, or the one the trusted
    /// identity header names. An account removed since its login has no session any more;
    /// a changed role holds at once.
    pub fn identify(&self, cookie: Option<&str>, header: Option<&str>) -> Option<Operator> {
        if let Some(token) = cookie.and_then(session_token) {
            let name = {
                let mut s = self.sessions.lock().unwrap_or_else(|p| p.into_inner());
                match s.get(token) {
                    Some(v) if v.created.elapsed() < SESSION_LIFETIME => Some(v.name.clone()),
                    Some(_) => {
                        s.remove(token);
                        None
                    }
                    None => None,
                }
            };
            if let Some(name) = name {
                match self.account(&name) {
                    Some(a) => {
                        return Some(Operator {
                            name: a.name,
                            role: a.role,
                            via: "password",
                        })
                    }
                    None => self.logout(token),
                }
            }
        }
        let name = header?.trim();
        self.identity_header.as_ref()?;
        check_name(name).ok()?;
        // A proxy's operator not listed here may look, no more.
        let role = self.account(name).map_or(Role::View, |a| a.role);
        Some(Operator {
            name: name.to_owned(),
            role,
            via: "proxy",
        })
    }

    /// Sessions open now.
    pub fn session_count(&self) -> usize {
        self.sessions
            .lock()
            .unwrap_or_else(|p| p.into_inner())
            .len()
    }
}

fn modified(p: &Path) -> Option<SystemTime> {
    std::fs::metadata(p).and_then(|m| m.modified()).ok()
}

/// The session token in a `Cookie` header, if it is well formed (64 hex digits).
pub fn session_token(cookie_header: &str) -> Option<&str> {
    cookie_header
        .split(';')
        .filter_map(|c| c.trim().split_once('='))
        .find(|(k, _)| *k == COOKIE)
        .map(|(_, v)| v)
        .filter(|v| v.len() == 64 && v.bytes().all(|b| b.is_ascii_hexdigit()))
}

/// The `Set-Cookie` header value of a new session.
pub fn set_cookie(token: &str) -> String {
    format!(
        "{COOKIE}={token}; HttpOnly; SameSite=Strict; Path=/; Max-Age={}",
        SESSION_LIFETIME.as_secs()
    )
}

/// The `Set-Cookie` header value that ends a session in the browser.
pub fn clear_cookie() -> String {
    format!("{COOKIE}=; HttpOnly; SameSite=Strict; Path=/; Max-Age=0")
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn accounts_file_lines_are_checked_and_named() {
        let p = Path::new("ops");
        let hash = hash_password("correct horse battery").unwrap();
        let ok = parse_accounts(
            p,
            &format!("# comment\nalice operate {hash}\n\nproxy.bob view -\n"),
        )
        .unwrap();
        assert_eq!(ok.len(), 2);
        assert_eq!(ok[0].role, Role::Operate);
        assert_eq!(ok[1].hash, None);
        for (text, says) in [
            (
                "alice operate".to_owned(),
                "line 1: expected NAME ROLE HASH",
            ),
            ("alice boss -".to_owned(), "role \"boss\""),
            ("al/ice view -".to_owned(), "not '/'"),
            ("alice view $md5$x".to_owned(), "not a PHC string"),
            (
                "a view -\na view -".to_owned(),
                "line 2: operator \"a\" is listed twice",
            ),
        ] {
            let e = parse_accounts(p, &text).unwrap_err().to_string();
            assert!(e.contains(says), "{text}: {e}");
        }
        assert!(hash_password("short").is_err());
    }

    #[test]
    fn a_login_opens_a_session_that_names_its_operator() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join(FILE_NAME);
        let hash = hash_password("correct horse battery").unwrap();
        write_accounts(
            &path,
            &[Account {
                name: "alice".into(),
                role: Role::Operate,
                hash: Some(hash),
            }],
        )
        .unwrap();
        let ops = Operators::open(Some(path.clone()), None).unwrap();
        assert!(ops.login_required());
        assert_eq!(ops.login("alice", "wrong password!"), Login::Refused);
        assert_eq!(
            ops.login("mallory", "correct horse battery"),
            Login::Refused
        );
        let Login::Ok(token, who) = ops.login("alice", "correct horse battery") else {
            panic!("refused");
        };
        assert_eq!((who.name.as_str(), who.role), ("alice", Role::Operate));
        let cookie = format!("other=1; {COOKIE}={token}");
        assert_eq!(ops.identify(Some(&cookie), None).unwrap().name, "alice");
        assert_eq!(ops.identify(Some("triax_session=abc"), None), None);
        assert_eq!(
            ops.identify(None, Some("alice")),
            None,
            "no header is trusted unless configured"
        );
        // The account goes: its session with it.
        std::thread::sleep(Duration::from_millis(20));
        write_accounts(&path, &[]).unwrap();
        assert_eq!(ops.identify(Some(&cookie), None), None);
        ops.logout(&token);
        assert_eq!(ops.session_count(), 0);
    }

    #[test]
    fn a_proxy_names_operators_with_the_role_listed_or_view() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join(FILE_NAME);
        write_accounts(
            &path,
            &[Account {
                name: "carol".into(),
                role: Role::Admin,
                hash: None,
            }],
        )
        .unwrap();
        let ops = Operators::open(Some(path), Some("X-Remote-User".into())).unwrap();
        assert_eq!(ops.identify(None, Some("carol")).unwrap().role, Role::Admin);
        assert_eq!(ops.identify(None, Some("dave")).unwrap().role, Role::View);
        assert_eq!(ops.identify(None, Some("bad name")), None);
        assert_eq!(
            ops.login("carol", "anything at all"),
            Login::Refused,
            "a proxy-named account has no password"
        );
    }
}
