//! Zenoh options shared by the lab's network commands (`push`, `serve`), defined once and
//! flattened into each, as in the Zenoh examples.

use std::path::PathBuf;

/// How the lab joins Zenoh.
#[derive(Debug, Clone, Default, clap::Args)]
pub struct ZenohArgs {
    /// Zenoh JSON5 configuration file (the base the other Zenoh flags override), e.g. one of
    /// deploy/zenoh/.
    #[arg(long, env = "TRIAX_ZENOH_CONFIG")]
    pub zenoh_config: Option<PathBuf>,
    /// Zenoh mode: peer or client (default: peer, or the file's).
    #[arg(long, env = "TRIAX_ZENOH_MODE", value_parser = ["peer", "client"])]
    pub zenoh_mode: Option<String>,
    /// Endpoint to connect to, e.g. tls/site-router.example:7448 (repeat or comma-separate).
    #[arg(long, short = 'e', env = "TRIAX_CONNECT", value_delimiter = ',')]
    pub connect: Vec<String>,
    /// Endpoint to listen on, e.g. tcp/0.0.0.0:7447 (repeat or comma-separate).
    #[arg(long, short = 'l', env = "TRIAX_LISTEN", value_delimiter = ',')]
    pub listen: Vec<String>,
    /// Turn off Zenoh multicast scouting.
    #[arg(long, env = "TRIAX_NO_MULTICAST_SCOUTING")]
    pub no_multicast_scouting: bool,
}

/// Why the Zenoh configuration could not be built.
#[derive(Debug, thiserror::Error)]
#[error("zenoh configuration `{key}`: {message}")]
pub struct ZenohConfigError {
    pub key: String,
    pub message: String,
}

impl ZenohArgs {
    /// Options for an embedded client or peer that connects to `endpoint` only: loopback tests
    /// and benches.
    pub fn connect_to(endpoint: &str, mode: &str) -> ZenohArgs {
        ZenohArgs {
            zenoh_mode: Some(mode.to_owned()),
            connect: vec![endpoint.to_owned()],
            no_multicast_scouting: true,
            ..ZenohArgs::default()
        }
    }

    /// The session configuration.
    pub fn config(&self) -> Result<zenoh::Config, ZenohConfigError> {
        let mut c = match &self.zenoh_config {
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
        let list = |items: &[String]| {
            // A list of strings always serialises.
            serde_json::to_string(items).expect("strings serialise")
        };
        match (&self.zenoh_mode, &self.zenoh_config) {
            (Some(m), _) => set("mode", format!("\"{m}\""))?,
            (None, None) => set("mode", "\"peer\"".into())?,
            (None, Some(_)) => {}
        }
        if !self.connect.is_empty() {
            set("connect/endpoints", list(&self.connect))?;
        }
        if !self.listen.is_empty() {
            set("listen/endpoints", list(&self.listen))?;
        } else if self.zenoh_config.is_none() {
            // A lab tool reaches out to routers; it has no reason to accept connections.
            set("listen/endpoints", "[]".into())?;
        }
        if self.no_multicast_scouting {
            set("scouting/multicast/enabled", "false".into())?;
        }
        Ok(c)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn flags_reach_the_zenoh_config() {
        let c = ZenohArgs::connect_to("tcp/127.0.0.1:7447", "client")
            .config()
            .unwrap();
        assert_eq!(c.get_json("mode").unwrap(), "\"client\"");
        assert_eq!(c.get_json("scouting/multicast/enabled").unwrap(), "false");
        assert!(c
            .get_json("connect/endpoints")
            .unwrap()
            .contains("127.0.0.1:7447"));
    }
}
