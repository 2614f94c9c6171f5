//! The gateway's signing key (PROTOCOL.md §6): made at first start, kept beside the store,
//! used by everything that puts or answers for the building.

use ed25519_dalek::SigningKey;
use triax_net::keys;
use triax_protocol::provenance::{sign_message, ATTACHMENT_LEN};
use triax_protocol::signing::to_hex;

use crate::clock::now_ns;
use crate::config::ProvenanceSettings;
use crate::error::GatewayError;

/// Signs the gateway's messages; signs nothing when `[provenance] sign = false`.
pub struct Signer {
    key: Option<SigningKey>,
}

impl Signer {
    /// Reads the key file, or makes it (and `<file>.pub`) when there is none.
    pub fn load(settings: &ProvenanceSettings) -> Result<Signer, GatewayError> {
        if !settings.sign {
            return Ok(Signer { key: None });
        }
        let path = &settings.key_file;
        let (key, origin) = keys::signing_key(path)
            .map_err(|e| GatewayError::Key(format!("provenance.key_file: {e}")))?;
        if origin == keys::Origin::Made {
            tracing::info!(
                key = %path.display(),
                public = %keys::public_path(path).display(),
                "made the gateway's signing key: give consumers the .pub"
            );
        }
        Ok(Signer { key: Some(key) })
    }

    /// A signer that signs nothing.
    pub fn off() -> Signer {
        Signer { key: None }
    }

    /// The attachment that signs `payload` on `key_expr` for a query's `nonce` ("" for a put).
    pub fn attachment(
        &self,
        key_expr: &str,
        nonce: &str,
        payload: &[u8],
    ) -> Option<[u8; ATTACHMENT_LEN]> {
        let key = self.key.as_ref()?;
        Some(sign_message(key, key_expr, nonce, now_ns(), payload))
    }

    /// Whether anything is signed (`[provenance] sign`).
    pub fn signs(&self) -> bool {
        self.key.is_some()
    }

    /// The public key consumers are to trust, in hex.
    pub fn public_key_hex(&self) -> Option<String> {
        self.key
            .as_ref()
            .map(|k| to_hex(k.verifying_key().as_bytes()))
    }
}

#[cfg(test)]
mod tests {
    use std::time::Duration;

    use triax_protocol::provenance::{verify_message, GatewayKeys};
    use triax_protocol::signing::public_key_from_hex;
    use triax_protocol::BuildingId;

    use super::*;

    #[test]
    fn a_key_made_at_first_start_is_the_one_read_at_the_next_and_its_public_half_verifies() {
        let dir = tempfile::tempdir().unwrap();
        let settings = ProvenanceSettings {
            key_file: dir.path().join("keys/gw.key"),
            seal_interval: Duration::from_millis(1),
            sign: true,
        };
        let first = Signer::load(&settings).unwrap();
        let again = Signer::load(&settings).unwrap();
        assert_eq!(first.public_key_hex(), again.public_key_hex());
        let public = std::fs::read_to_string(dir.path().join("keys/gw.key.pub")).unwrap();
        assert_eq!(Some(public.trim().to_owned()), first.public_key_hex());
        let mut trusted = GatewayKeys::new();
        trusted.trust(
            BuildingId::new("hq").unwrap(),
            public_key_from_hex(&public).unwrap(),
        );
        let a = again.attachment("triax/hq/heartbeat", "", b"{}").unwrap();
        verify_message(&trusted, "triax/hq/heartbeat", "", b"{}", Some(&a)).unwrap();
        #[cfg(unix)]
        {
            use std::os::unix::fs::PermissionsExt;
            let mode = std::fs::metadata(&settings.key_file)
                .unwrap()
                .permissions()
                .mode();
            assert_eq!(mode & 0o077, 0, "the secret is its owner's only: {mode:o}");
        }
        std::fs::write(&settings.key_file, "not hex").unwrap();
        let e = Signer::load(&settings).err().unwrap().to_string();
        assert!(
            e.contains("provenance.key_file") && e.contains("gw.key"),
            "{e}"
        );
        let off = Signer::load(&ProvenanceSettings {
            sign: false,
            ..settings
        })
        .unwrap();
        assert!(off.attachment("triax/hq/heartbeat", "", b"{}").is_none());
    }
}
