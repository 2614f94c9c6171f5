//! Key files the services share: a program's own Ed25519 signing key, made at its first start,
//! and the gateway public keys a consumer trusts (PROTOCOL.md §6).
//!
//! Keys are the texts of `triax_protocol::signing`: 64 hex characters and a newline.

use std::collections::BTreeMap;
use std::io::Write;
use std::path::{Path, PathBuf};

use ed25519_dalek::SigningKey;
use triax_protocol::provenance::GatewayKeys;
use triax_protocol::signing::{public_key_from_hex, signing_key_from_hex, to_hex};
use triax_protocol::BuildingId;

use crate::ConfigError;

/// Why a key file could not be read or made.
#[derive(Debug, thiserror::Error)]
pub enum KeyFileError {
    #[error("key file {path}: {message}")]
    Parse { path: PathBuf, message: String },
    #[error("key file {path}: {source}")]
    Io {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
}

/// Whether [`signing_key`] read the key or made it.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Origin {
    Read,
    Made,
}

/// Reads the secret key at `path`; when there is none, makes one there (readable by its owner
/// only, never over an existing file) with its public key in `<path>.pub`.
pub fn signing_key(path: &Path) -> Result<(SigningKey, Origin), KeyFileError> {
    let io = |p: &Path| {
        let p = p.to_owned();
        move |source| KeyFileError::Io { path: p, source }
    };
    match std::fs::read_to_string(path) {
        Ok(text) => {
            let key = signing_key_from_hex(&text).map_err(|e| KeyFileError::Parse {
                path: path.to_owned(),
                message: e.to_string(),
            })?;
            return Ok((key, Origin::Read));
        }
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {}
        Err(e) => return Err(io(path)(e)),
    }
    let key = SigningKey::generate(&mut rand::rngs::OsRng);
    if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
        std::fs::create_dir_all(dir).map_err(io(dir))?;
    }
    let mut options = std::fs::OpenOptions::new();
    // Two programs started at once on one file never overwrite each other's key: the second
    // fails here, and says so.
    options.write(true).create_new(true);
    #[cfg(unix)]
    std::os::unix::fs::OpenOptionsExt::mode(&mut options, 0o600);
    let mut file = options.open(path).map_err(io(path))?;
    file.write_all(format!("{}\n", to_hex(&key.to_bytes())).as_bytes())
        .and_then(|()| file.sync_all())
        .map_err(io(path))?;
    let public = public_path(path);
    std::fs::write(
        &public,
        format!("{}\n", to_hex(key.verifying_key().as_bytes())),
    )
    .map_err(io(&public))?;
    Ok((key, Origin::Made))
}

/// `<key_file>.pub`, where [`signing_key`] writes the public half.
pub fn public_path(key_file: &Path) -> PathBuf {
    let mut name = key_file.as_os_str().to_owned();
    name.push(".pub");
    name.into()
}

/// The `[gateways]` table of a consumer's configuration: per building, its gateway's public key,
/// as 64 hex characters or the path of a file holding them (relative to the working
/// directory). `field` names the table in errors.
pub fn gateway_keys(
    field: &str,
    table: &BTreeMap<String, String>,
) -> Result<GatewayKeys, ConfigError> {
    let mut keys = GatewayKeys::new();
    for (building, value) in table {
        let name = format!("{field}.{building}");
        let b = BuildingId::new(building.as_str())
            .map_err(|e| ConfigError::invalid(&name, e.to_string()))?;
        let text = if value.len() == 64 && value.chars().all(|c| c.is_ascii_hexdigit()) {
            value.clone()
        } else {
            std::fs::read_to_string(value)
                .map_err(|e| ConfigError::invalid(&name, format!("cannot read {value}: {e}")))?
        };
        let key = public_key_from_hex(&text)
            .map_err(|e| ConfigError::invalid(&name, format!("{value}: {e}")))?;
        keys.trust(b, key);
    }
    Ok(keys)
}

/// [`gateway_keys`] of a service's `[gateways]` table; None when the table is empty (the
/// service then takes every message on trust).
pub fn trusted_gateways(
    table: &BTreeMap<String, String>,
) -> Result<Option<std::sync::Arc<GatewayKeys>>, ConfigError> {
    if table.is_empty() {
        return Ok(None);
    }
    Ok(Some(std::sync::Arc::new(gateway_keys("gateways", table)?)))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_key_made_once_is_read_after_and_its_public_half_is_trusted_from_a_table() {
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join("keys/gw.key");
        let (made, origin) = signing_key(&path).unwrap();
        assert_eq!(origin, Origin::Made);
        let (read, origin) = signing_key(&path).unwrap();
        assert_eq!((read.to_bytes(), origin), (made.to_bytes(), Origin::Read));
        #[cfg(unix)]
        {
            use std::os::unix::fs::PermissionsExt;
            let mode = std::fs::metadata(&path).unwrap().permissions().mode();
            assert_eq!(mode & 0o077, 0, "the secret is its owner's only: {mode:o}");
        }
        let public = public_path(&path);
        let hex = to_hex(made.verifying_key().as_bytes());
        let table = BTreeMap::from([
            ("hq".to_owned(), public.display().to_string()),
            ("b2".to_owned(), hex.clone()),
        ]);
        let keys = gateway_keys("gateways", &table).unwrap();
        for b in ["hq", "b2"] {
            assert_eq!(
                keys.keys(&BuildingId::new(b).unwrap()),
                [made.verifying_key()]
            );
        }
        let bad = BTreeMap::from([("hq".to_owned(), "missing.pub".to_owned())]);
        let e = gateway_keys("gateways", &bad).unwrap_err().to_string();
        assert!(
            e.contains("gateways.hq") && e.contains("missing.pub"),
            "{e}"
        );
        let bad = BTreeMap::from([("h q".to_owned(), hex)]);
        assert!(gateway_keys("gateways", &bad).is_err());
        std::fs::write(&path, "zz").unwrap();
        assert!(matches!(
            signing_key(&path),
            Err(KeyFileError::Parse { .. })
        ));
    }
}
