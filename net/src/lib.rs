//! How a Triax program joins Zenoh: one settings type for the `[zenoh]` table of a TOML file,
//! one set of command-line flags flattened into every binary (as in Zenoh's own examples), and
//! one function that turns them into a `zenoh::Config`.
//!
//! The JSON5 file, when given, is the base; the other settings override it. A setting left unset
//! keeps the file's value, or, without a file, Zenoh's default (multicast scouting on), except
//! the mode, which defaults to `peer`: a building needs no router.
//!
//! Also what the services share to read their own configuration file: [`read_toml`] and
//! [`ConfigError`], whose `zenoh.<field>` errors come from [`ZenohSettingsError`]; and their
//! key files ([`keys`]).

pub mod keys;

use std::path::{Path, PathBuf};

use serde::Deserialize;

/// How a program joins Zenoh.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Deserialize, clap::ValueEnum)]
#[serde(rename_all = "lowercase")]
pub enum ZenohMode {
    /// An embedded peer: talks to other peers directly, no router needed.
    Peer,
    /// A client of a router (`connect` names it).
    Client,
}

impl ZenohMode {
    fn as_str(self) -> &'static str {
        match self {
            ZenohMode::Peer => "peer",
            ZenohMode::Client => "client",
        }
    }
}

/// The `[zenoh]` table of a configuration file.
#[derive(Debug, Clone, Default, PartialEq, Eq, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ZenohSettings {
    /// Zenoh JSON5 configuration file, the base the other settings override.
    pub config_file: Option<PathBuf>,
    pub mode: Option<ZenohMode>,
    /// Endpoints to listen on, e.g. `tcp/0.0.0.0:7447`; empty keeps the file's or Zenoh's.
    #[serde(default)]
    pub listen: Vec<String>,
    /// Endpoints to connect to, e.g. `tls/site-router:7448`.
    #[serde(default)]
    pub connect: Vec<String>,
    pub multicast_scouting: Option<bool>,
}

/// The same settings as command-line flags (and `TRIAX_*` environment variables), to
/// `#[command(flatten)]` into a binary's arguments. Flags override the file.
#[derive(Debug, Clone, Default, clap::Args)]
pub struct ZenohArgs {
    /// Zenoh JSON5 configuration file (the base the other Zenoh flags override).
    #[arg(long, env = "TRIAX_ZENOH_CONFIG")]
    pub zenoh_config: Option<PathBuf>,
    /// Zenoh mode.
    #[arg(long, value_enum, env = "TRIAX_ZENOH_MODE")]
    pub zenoh_mode: Option<ZenohMode>,
    /// Zenoh endpoint to listen on, e.g. tcp/0.0.0.0:7447 (repeat or comma-separate).
    #[arg(long, env = "TRIAX_LISTEN", value_delimiter = ',')]
    pub listen: Vec<String>,
    /// Zenoh endpoint to connect to, e.g. tcp/router:7447 (repeat or comma-separate).
    #[arg(long, env = "TRIAX_CONNECT", value_delimiter = ',')]
    pub connect: Vec<String>,
    /// Turn off Zenoh multicast scouting.
    #[arg(long, env = "TRIAX_NO_MULTICAST_SCOUTING")]
    pub no_multicast_scouting: bool,
}

impl ZenohArgs {
    /// Puts the flags that were given over `settings`.
    pub fn apply_to(&self, settings: &mut ZenohSettings) {
        if let Some(f) = &self.zenoh_config {
            settings.config_file = Some(f.clone());
        }
        if let Some(m) = self.zenoh_mode {
            settings.mode = Some(m);
        }
        if !self.listen.is_empty() {
            settings.listen = self.listen.clone();
        }
        if !self.connect.is_empty() {
            settings.connect = self.connect.clone();
        }
        if self.no_multicast_scouting {
            settings.multicast_scouting = Some(false);
        }
    }

    /// The settings the flags alone describe.
    pub fn settings(&self) -> ZenohSettings {
        let mut s = ZenohSettings::default();
        self.apply_to(&mut s);
        s
    }
}

/// Why a program's configuration was refused, naming the file or the field: what every Triax
/// service reports for its TOML file, flags and environment.
#[derive(Debug, thiserror::Error)]
pub enum ConfigError {
    #[error("cannot read config file {path}: {source}")]
    Read {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("config file {path}: {message}")]
    Parse { path: PathBuf, message: String },
    #[error("config field `{field}`: {reason}")]
    Invalid { field: String, reason: String },
}

impl ConfigError {
    /// A field whose value cannot work, and why.
    pub fn invalid(field: impl Into<String>, reason: impl Into<String>) -> ConfigError {
        ConfigError::Invalid {
            field: field.into(),
            reason: reason.into(),
        }
    }
}

impl From<ZenohSettingsError> for ConfigError {
    fn from(e: ZenohSettingsError) -> ConfigError {
        ConfigError::invalid(format!("zenoh.{}", e.field), e.reason)
    }
}

/// Reads the TOML file at `path` into `T`.
pub fn read_toml<T: serde::de::DeserializeOwned>(path: &Path) -> Result<T, ConfigError> {
    let text = std::fs::read_to_string(path).map_err(|source| ConfigError::Read {
        path: path.to_owned(),
        source,
    })?;
    parse_toml(&text, path)
}

/// Parses `text`, the content of the file `path`, into `T`; the error names the file, and the
/// parser's message the line, the column and the field.
pub fn parse_toml<T: serde::de::DeserializeOwned>(
    text: &str,
    path: &Path,
) -> Result<T, ConfigError> {
    toml::from_str(text).map_err(|e| ConfigError::Parse {
        path: path.to_owned(),
        message: e.to_string().trim_end().to_owned(),
    })
}

/// A setting that cannot work, named by its field in the `[zenoh]` table.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("config field `zenoh.{field}`: {reason}")]
pub struct ZenohSettingsError {
    pub field: String,
    pub reason: String,
}

/// Zenoh refused the configuration built from the settings.
#[derive(Debug, thiserror::Error)]
#[error("zenoh configuration `{key}`: {message}")]
pub struct ZenohConfigError {
    pub key: String,
    pub message: String,
}

impl ZenohSettings {
    /// Settings for tests, demos and benches: loopback only, multicast scouting off.
    pub fn loopback(mode: ZenohMode, listen: Vec<String>, connect: Vec<String>) -> ZenohSettings {
        ZenohSettings {
            config_file: None,
            mode: Some(mode),
            listen,
            connect,
            multicast_scouting: Some(false),
        }
    }

    /// Checks what can be checked before Zenoh starts: endpoint shapes, a client with nowhere
    /// to connect, a configuration file that is not there.
    pub fn validate(&self) -> Result<(), ZenohSettingsError> {
        let invalid = |field: String, reason: String| Err(ZenohSettingsError { field, reason });
        for (field, list) in [("listen", &self.listen), ("connect", &self.connect)] {
            for (i, e) in list.iter().enumerate() {
                // A Zenoh endpoint is `<protocol>/<address>`; the rest is Zenoh's to check.
                let ok = e
                    .split_once('/')
                    .is_some_and(|(p, a)| !p.is_empty() && !a.is_empty());
                if !ok {
                    return invalid(
                        format!("{field}[{i}]"),
                        format!("{e:?} is not a Zenoh endpoint like \"tcp/0.0.0.0:7447\""),
                    );
                }
            }
        }
        if self.mode == Some(ZenohMode::Client)
            && self.connect.is_empty()
            && self.config_file.is_none()
        {
            return invalid(
                "connect".into(),
                "client mode needs at least one router endpoint to connect to".into(),
            );
        }
        if let Some(p) = &self.config_file {
            if !p.is_file() {
                return invalid(
                    "config_file".into(),
                    format!("{} is not a readable file", p.display()),
                );
            }
        }
        Ok(())
    }

    /// The session configuration: the file (or Zenoh's defaults), then the settings on top.
    pub fn to_config(&self) -> Result<zenoh::Config, ZenohConfigError> {
        let mut c = match &self.config_file {
            Some(path) => zenoh::Config::from_file(path).map_err(|e| ZenohConfigError {
                key: format!("file {}", path.display()),
                message: e.to_string(),
            })?,
            None => zenoh::Config::default(),
        };
        let mut set = |key: &str, value: String| {
            c.insert_json5(key, &value).map_err(|e| ZenohConfigError {
                key: key.to_owned(),
                message: e.to_string(),
            })
        };
        // A list of strings always serialises to JSON.
        let list = |items: &[String]| serde_json::to_string(items).expect("strings serialise");
        match (self.mode, &self.config_file) {
            (Some(m), _) => set("mode", format!("\"{}\"", m.as_str()))?,
            (None, None) => set("mode", "\"peer\"".into())?,
            (None, Some(_)) => {}
        }
        if !self.listen.is_empty() {
            set("listen/endpoints", list(&self.listen))?;
        }
        if !self.connect.is_empty() {
            set("connect/endpoints", list(&self.connect))?;
        }
        if let Some(on) = self.multicast_scouting {
            set("scouting/multicast/enabled", on.to_string())?;
        }
        Ok(c)
    }

    /// [`to_config`](Self::to_config) for a session that publishes high-rate streams with drop
    /// congestion control: its transmit queues set as [`PUBLISHER_TX_QUEUE_BATCHES`] says why,
    /// and the messages it takes bounded as [`PUBLISHER_MAX_MESSAGE_BYTES`] says, unless a
    /// configuration file is given (whose settings then stand).
    pub fn to_publisher_config(&self) -> Result<zenoh::Config, ZenohConfigError> {
        let mut c = self.to_config()?;
        if self.config_file.is_some() {
            return Ok(c);
        }
        let queue = "transport/link/tx/queue";
        for (key, value) in [
            (format!("{queue}/size/data"), PUBLISHER_TX_QUEUE_BATCHES),
            (format!("{queue}/size/data_low"), PUBLISHER_TX_QUEUE_BATCHES),
            (
                format!("{queue}/congestion_control/drop/wait_before_drop"),
                PUBLISHER_WAIT_BEFORE_DROP_US,
            ),
            (
                "transport/link/rx/max_message_size".to_owned(),
                PUBLISHER_MAX_MESSAGE_BYTES,
            ),
        ] {
            c.insert_json5(&key, &value.to_string())
                .map_err(|e| ZenohConfigError {
                    key,
                    message: e.to_string(),
                })?;
        }
        Ok(c)
    }
}

/// [`ZenohSettings::to_config`] for a program that only reaches out (a lab tool, an exporter,
/// a console): it listens nowhere unless `listen` or a configuration file says so, where
/// Zenoh's default peer would accept connections on every interface.
pub fn outbound_config(settings: &ZenohSettings) -> Result<zenoh::Config, OutboundConfigError> {
    settings.validate()?;
    let mut config = settings.to_config()?;
    if settings.listen.is_empty() && settings.config_file.is_none() {
        config
            .insert_json5("listen/endpoints", "[]")
            .map_err(|e| ZenohConfigError {
                key: "listen/endpoints".into(),
                message: e.to_string(),
            })?;
    }
    Ok(config)
}

/// Why [`outbound_config`] refused the settings.
#[derive(Debug, thiserror::Error)]
pub enum OutboundConfigError {
    #[error(transparent)]
    Settings(#[from] ZenohSettingsError),
    #[error(transparent)]
    Config(#[from] ZenohConfigError),
}

/// A Zenoh error as a user should read it: its message without the source location Zenoh
/// appends (`… at /path/to/zenoh/src/file.rs:447.`), which names a build, not a cause.
pub fn zenoh_cause(e: &(dyn std::error::Error + Send + Sync)) -> String {
    let text = e.to_string();
    match text.rfind(" at ") {
        Some(i) if text[i..].contains(".rs:") => text[..i].trim_end().to_owned(),
        _ => text,
    }
}

/// Transmit-queue settings of a session that publishes high-rate streams with drop congestion
/// control (the gateway), for [`ZenohSettings::to_publisher_config`].
///
/// Zenoh keeps, per link and priority, a queue of 2 batches of 64 KiB by default, and a
/// droppable message waits up to 1 ms for room before it is dropped. For a publisher that must
/// never be held up by one consumer, that wait is the problem: a stalled consumer's link is
/// always full, so every put to it waits the whole millisecond, and the publisher is throttled to
/// a thousand messages a second for everyone. So: the deepest queue Zenoh allows (16 batches,
/// 1 MiB a link), which absorbs a healthy consumer's hiccups, and no wait at all, so that a full
/// link costs its put nothing.
pub const PUBLISHER_TX_QUEUE_BATCHES: u32 = 16;
pub const PUBLISHER_WAIT_BEFORE_DROP_US: u32 = 0;

/// The largest message the gateway's session reassembles, for
/// [`ZenohSettings::to_publisher_config`]. Zenoh's default is 1 GiB: a node, trusted with
/// nothing but its key, could have the gateway gather that much per link before any of the
/// gateway's checks sees it. The largest message PROTOCOL.md allows is 8 MiB (a gateway's
/// status), a raw batch at most 196 711 bytes; Zenoh drops a longer message and keeps the link.
pub const PUBLISHER_MAX_MESSAGE_BYTES: u32 = 16 << 20;

/// A TCP port on 127.0.0.1 that was free a moment ago, for demos, tests and benches that start
/// a Zenoh listener other sessions must connect to: Zenoh 1.10's stable API does not report the
/// port a `:0` listener bound.
pub fn free_loopback_port() -> std::io::Result<u16> {
    Ok(std::net::TcpListener::bind("127.0.0.1:0")?
        .local_addr()?
        .port())
}

#[cfg(test)]
mod tests {
    use super::*;
    use clap::Parser;

    #[derive(Parser)]
    struct Cli {
        #[command(flatten)]
        zenoh: ZenohArgs,
    }

    #[test]
    fn settings_reach_the_zenoh_config() {
        let s =
            ZenohSettings::loopback(ZenohMode::Client, vec![], vec!["tcp/127.0.0.1:7447".into()]);
        s.validate().unwrap();
        let c = s.to_config().unwrap();
        assert_eq!(c.get_json("mode").unwrap(), "\"client\"");
        assert_eq!(c.get_json("scouting/multicast/enabled").unwrap(), "false");
        assert!(c
            .get_json("connect/endpoints")
            .unwrap()
            .contains("127.0.0.1:7447"));
        assert_eq!(
            ZenohSettings::default()
                .to_config()
                .unwrap()
                .get_json("mode")
                .unwrap(),
            "\"peer\"",
            "a building needs no router"
        );
    }

    #[test]
    fn a_publisher_never_waits_on_a_full_link() {
        let s = ZenohSettings::default();
        let c = s.to_publisher_config().unwrap();
        assert_eq!(
            c.get_json("transport/link/rx/buffer_size").unwrap(),
            s.to_config()
                .unwrap()
                .get_json("transport/link/rx/buffer_size")
                .unwrap(),
            "Zenoh's own receive buffers: the gateway holds no sample past its callback"
        );
        assert_eq!(
            c.get_json("transport/link/rx/max_message_size").unwrap(),
            (16 << 20).to_string()
        );
        let q = "transport/link/tx/queue";
        assert_eq!(c.get_json(&format!("{q}/size/data")).unwrap(), "16");
        assert_eq!(
            c.get_json(&format!("{q}/congestion_control/drop/wait_before_drop"))
                .unwrap(),
            "0"
        );
        assert_eq!(
            s.to_config()
                .unwrap()
                .get_json(&format!("{q}/size/data"))
                .unwrap(),
            "2",
            "Zenoh's default elsewhere"
        );
    }

    #[test]
    fn flags_override_the_file() {
        let mut s: ZenohSettings = toml::from_str(
            "mode = \"peer\"\nlisten = [\"tcp/0.0.0.0:7447\"]\nmulticast_scouting = true\n",
        )
        .unwrap();
        let cli = Cli::parse_from([
            "x",
            "--zenoh-mode",
            "client",
            "--connect",
            "tcp/a:1,tcp/b:2",
            "--no-multicast-scouting",
        ]);
        cli.zenoh.apply_to(&mut s);
        assert_eq!(s.mode, Some(ZenohMode::Client));
        assert_eq!(s.listen, ["tcp/0.0.0.0:7447"], "unset flags keep the file");
        assert_eq!(s.connect, ["tcp/a:1", "tcp/b:2"]);
        assert_eq!(s.multicast_scouting, Some(false));
    }

    #[test]
    fn bad_settings_name_their_field() {
        let mut s = ZenohSettings {
            listen: vec!["0.0.0.0:7447".into()],
            ..ZenohSettings::default()
        };
        let e = s.validate().unwrap_err();
        assert_eq!(e.field, "listen[0]");
        assert!(e.to_string().contains("zenoh.listen[0]"), "{e}");
        s.listen.clear();
        s.mode = Some(ZenohMode::Client);
        assert_eq!(s.validate().unwrap_err().field, "connect");
        s.config_file = Some("/nonexistent/zenoh.json5".into());
        assert_eq!(s.validate().unwrap_err().field, "config_file");
    }
}
