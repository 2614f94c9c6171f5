//! The example Zenoh configurations under deploy/zenoh/ are valid for the Zenoh this workspace
//! builds with: each parses with `zenoh::Config::from_file`, and the settings the deployment
//! guide relies on (mode, no multicast scouting, mTLS, access control on) are what they say.

use std::path::PathBuf;

fn deploy_dir() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../deploy/zenoh")
}

fn load(name: &str) -> zenoh::Config {
    let path = deploy_dir().join(name);
    zenoh::Config::from_file(&path).unwrap_or_else(|e| panic!("{}: {e}", path.display()))
}

#[test]
fn every_example_config_parses() {
    let mut names: Vec<String> = std::fs::read_dir(deploy_dir())
        .expect("deploy/zenoh exists")
        .filter_map(|e| e.ok())
        .map(|e| e.file_name().to_string_lossy().into_owned())
        .filter(|n| n.ends_with(".json5"))
        .collect();
    names.sort();
    assert_eq!(
        names,
        [
            "gateway-client.json5",
            "lab-client.json5",
            "lab-router.json5",
            "site-router.json5"
        ]
    );
    for name in &names {
        let c = load(name);
        assert_eq!(
            c.get_json("scouting/multicast/enabled").unwrap(),
            "false",
            "{name}"
        );
    }
}

#[test]
fn routers_use_mtls_and_access_control() {
    for name in ["site-router.json5", "lab-router.json5"] {
        let c = load(name);
        assert_eq!(c.get_json("mode").unwrap(), "\"router\"", "{name}");
        assert_eq!(
            c.get_json("transport/link/tls/enable_mtls").unwrap(),
            "true",
            "{name}"
        );
        assert_eq!(
            c.get_json("access_control/enabled").unwrap(),
            "true",
            "{name}"
        );
        assert_eq!(
            c.get_json("access_control/default_permission").unwrap(),
            "\"deny\"",
            "{name}"
        );
    }
    let site = load("site-router.json5")
        .get_json("access_control/subjects")
        .unwrap();
    assert!(site.contains("triax-lab"), "{site}");
    for name in ["gateway-client.json5", "lab-client.json5"] {
        assert_eq!(load(name).get_json("mode").unwrap(), "\"client\"", "{name}");
    }
}
