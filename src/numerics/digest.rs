//! SHA-256 digests as lowercase hex: the hashes that tie outputs to their inputs (provenance
//! metadata, campaign config hashes). In `numerics` so that the model, io and campaign layers
//! share one implementation without depending on each other.

use sha2::{Digest, Sha256};

/// Hex SHA-256 digest of `bytes`.
pub fn sha256_hex(bytes: &[u8]) -> String {
    hex(&Sha256::digest(bytes))
}

/// Hex SHA-256 digest of several parts, each preceded by its length (so that moving bytes
/// from one part to the next changes the digest).
pub fn sha256_parts_hex(parts: &[&[u8]]) -> String {
    let mut h = Sha256::new();
    for p in parts {
        h.update((p.len() as u64).to_le_bytes());
        h.update(p);
    }
    hex(&h.finalize())
}

/// Lowercase hex of a digest.
pub fn hex(digest: &[u8]) -> String {
    digest.iter().map(|b| format!("{b:02x}")).collect()
}
