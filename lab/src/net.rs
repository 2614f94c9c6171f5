//! How the lab's network commands (`push`, `serve`) join Zenoh: the options shared by every
//! Triax program ([`triax_net::ZenohArgs`]), listening nowhere unless told.

use triax_net::{OutboundConfigError, ZenohArgs};

/// Why the lab's Zenoh configuration was refused.
pub type NetError = OutboundConfigError;

/// The session configuration for the lab's command-line options: a lab tool reaches out to
/// routers and gateways and has no reason to accept connections
/// ([`triax_net::outbound_config`]).
pub fn zenoh_config(args: &ZenohArgs) -> Result<zenoh::Config, NetError> {
    triax_net::outbound_config(&args.settings())
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
