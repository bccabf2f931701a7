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

#[cfg(test)]
mod tests {
    use super::*;

    /// Oracle: the FIPS 180-2 appendix B.1 test vector ("abc"), and `sha256sum` of the
    /// length-prefixed bytes for the parts digest (what freefall has always written, so the
    /// hashes of identical inputs stay the same across sha2 versions).
    #[test]
    fn sha256_matches_published_vectors() {
        assert_eq!(
            sha256_hex(b"abc"),
            "ba7816bf8f01cfea414140de5dae2223b00361a396177a9cb410ff61f20015ad"
        );
        assert_eq!(
            sha256_hex(b""),
            "e3b0c44298fc1c149afbf4c8996fb92427ae41e4649b934ca495991b7852b855"
        );
        assert_eq!(
            sha256_parts_hex(&[b"ab", b"c"]),
            PARTS_AB_C_SHA256_BY_SHA256SUM
        );
    }

    /// `printf '\x02\0\0\0\0\0\0\0ab\x01\0\0\0\0\0\0\0c' | sha256sum`
    const PARTS_AB_C_SHA256_BY_SHA256SUM: &str =
        "43ee655579de01ca739b3f95c1c2d3f46d353b2c0df818064ea594506cdb2617";
}
