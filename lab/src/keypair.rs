//! The lab's Ed25519 key pair: generated once by `triax-lab keygen`, kept as two hex text files
//! (`lab.key`, the 32-byte secret seed, readable by its owner only; `lab.pub`, the public key
//! every gateway lists among its trusted lab keys).
//!
//! The texts are those of `triax_protocol::signing` (64 lowercase hex characters and a newline),
//! so a key file can be read, copied into a gateway's configuration and compared by eye.

use std::path::{Path, PathBuf};

use triax_protocol::signing::{signing_key_from_hex, to_hex, LabPublicKey, LabSigningKey};

/// File name of the secret key written by `keygen`.
pub const SECRET_FILE: &str = "lab.key";
/// File name of the public key written by `keygen`.
pub const PUBLIC_FILE: &str = "lab.pub";

/// Why a key file could not be read.
#[derive(Debug, thiserror::Error)]
pub enum KeyFileError {
    #[error("cannot read key file {path}: {source}")]
    Read {
        path: PathBuf,
        #[source]
        source: std::io::Error,
    },
    #[error("key file {path}: {source}")]
    Parse {
        path: PathBuf,
        #[source]
        source: triax_protocol::signing::SigningError,
    },
}

/// A fresh key pair from the operating system's random source.
pub fn generate() -> LabSigningKey {
    LabSigningKey::generate(&mut rand::rngs::OsRng)
}

/// The secret key file's text.
pub fn secret_text(key: &LabSigningKey) -> String {
    format!("{}\n", to_hex(&key.to_bytes()))
}

/// The public key file's text.
pub fn public_text(key: &LabPublicKey) -> String {
    format!("{}\n", to_hex(key.as_bytes()))
}

/// Reads a secret key file written by `keygen`.
pub fn read_secret(path: &Path) -> Result<LabSigningKey, KeyFileError> {
    let text = std::fs::read_to_string(path).map_err(|source| KeyFileError::Read {
        path: path.to_owned(),
        source,
    })?;
    signing_key_from_hex(&text).map_err(|source| KeyFileError::Parse {
        path: path.to_owned(),
        source,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use triax_protocol::signing::public_key_from_hex;

    #[test]
    fn texts_round_trip() {
        let key = generate();
        let dir = tempfile::tempdir().unwrap();
        let path = dir.path().join(SECRET_FILE);
        std::fs::write(&path, secret_text(&key)).unwrap();
        assert_eq!(read_secret(&path).unwrap().to_bytes(), key.to_bytes());
        let public = public_text(&key.verifying_key());
        assert_eq!(public.len(), 65);
        assert_eq!(public_key_from_hex(&public).unwrap(), key.verifying_key());
        assert_ne!(generate().to_bytes(), key.to_bytes(), "fresh randomness");
        std::fs::write(&path, "zz").unwrap();
        assert!(matches!(
            read_secret(&path),
            Err(KeyFileError::Parse { .. })
        ));
    }
}
