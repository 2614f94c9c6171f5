//! How the lab's network commands (`push`, `serve`) join Zenoh: the options shared by every
//! Triax program ([`triax_net::ZenohArgs`]), with one rule of the lab's own.

use triax_net::{ZenohArgs, ZenohConfigError, ZenohSettingsError};

/// Why the lab's Zenoh configuration was refused.
#[derive(Debug, thiserror::Error)]
pub enum NetError {
    #[error(transparent)]
    Settings(#[from] ZenohSettingsError),
    #[error(transparent)]
    Config(#[from] ZenohConfigError),
}

/// The session configuration for the lab's command-line options.
pub fn zenoh_config(args: &ZenohArgs) -> Result<zenoh::Config, NetError> {
    let settings = args.settings();
    settings.validate()?;
    let mut config = settings.to_config()?;
    if settings.listen.is_empty() && settings.config_file.is_none() {
        // A lab tool reaches out to routers and gateways; it has no reason to accept
        // connections, which Zenoh's default peer would.
        config
            .insert_json5("listen/endpoints", "[]")
            .map_err(|e| ZenohConfigError {
                key: "listen/endpoints".into(),
                message: e.to_string(),
            })?;
    }
    Ok(config)
}

#[cfg(test)]
mod tests {
    use super::*;
    use triax_net::ZenohMode;

    #[test]
    fn the_lab_listens_only_when_told() {
        let args = ZenohArgs {
            zenoh_mode: Some(ZenohMode::Client),
            connect: vec!["tcp/127.0.0.1:7447".into()],
            no_multicast_scouting: true,
            ..ZenohArgs::default()
        };
        let c = zenoh_config(&args).unwrap();
        assert_eq!(c.get_json("mode").unwrap(), "\"client\"");
        assert_eq!(c.get_json("listen/endpoints").unwrap(), "[]");
        let listening = ZenohArgs {
            listen: vec!["tcp/127.0.0.1:7448".into()],
            ..args
        };
        assert!(zenoh_config(&listening)
            .unwrap()
            .get_json("listen/endpoints")
            .unwrap()
            .contains("7448"));
        let client_nowhere = ZenohArgs {
            zenoh_mode: Some(ZenohMode::Client),
            ..ZenohArgs::default()
        };
        assert!(matches!(
            zenoh_config(&client_nowhere),
            Err(NetError::Settings(_))
        ));
    }
}
