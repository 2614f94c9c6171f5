//! The Zenoh session configuration: the optional JSON5 file as the base, then the gateway's
//! settings on top.

use crate::config::{ZenohMode, ZenohSettings};

/// Why a Zenoh configuration could not be built.
#[derive(Debug, thiserror::Error)]
#[error("zenoh configuration `{key}`: {message}")]
pub struct ZenohConfigError {
    pub key: String,
    pub message: String,
}

fn json_list(items: &[String]) -> String {
    // A list of strings always serialises.
    serde_json::to_string(items).expect("strings serialise")
}

/// Builds the session configuration.
pub fn zenoh_config(s: &ZenohSettings) -> Result<zenoh::Config, ZenohConfigError> {
    let mut c = match &s.config_file {
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
    match (&s.mode, &s.config_file) {
        (Some(ZenohMode::Client), _) => set("mode", "\"client\"".into())?,
        (Some(ZenohMode::Peer), _) | (None, None) => set("mode", "\"peer\"".into())?,
        (None, Some(_)) => {}
    }
    if !s.listen.is_empty() {
        set("listen/endpoints", json_list(&s.listen))?;
    }
    if !s.connect.is_empty() {
        set("connect/endpoints", json_list(&s.connect))?;
    }
    if let Some(on) = s.multicast_scouting {
        set("scouting/multicast/enabled", on.to_string())?;
    }
    Ok(c)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn settings_reach_the_zenoh_config() {
        let c = zenoh_config(&ZenohSettings {
            config_file: None,
            mode: None,
            listen: vec!["tcp/127.0.0.1:0".into()],
            connect: vec![],
            multicast_scouting: Some(false),
        })
        .unwrap();
        assert_eq!(c.get_json("mode").unwrap(), "\"peer\"");
        assert_eq!(c.get_json("scouting/multicast/enabled").unwrap(), "false");
        assert!(c
            .get_json("listen/endpoints")
            .unwrap()
            .contains("127.0.0.1:0"));
    }
}
