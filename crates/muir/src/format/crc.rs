//! CRC-32 (IEEE 802.3, reflected, polynomial 0xEDB88320), table driven.
#![deny(clippy::indexing_slicing)]

const TABLE: [u32; 256] = {
    let mut t = [0u32; 256];
    let mut rest: &mut [u32] = &mut t;
    let mut i = 0;
    while let [entry, tail @ ..] = rest {
        let mut c = i;
        let mut k = 0;
        while k < 8 {
            c = if c & 1 != 0 { 0xEDB8_8320 ^ (c >> 1) } else { c >> 1 };
            k += 1;
        }
        *entry = c;
        rest = tail;
        i += 1;
    }
    t
};

/// The slicing-by-8 tables: `SLICES[k][b]` is the CRC of byte `b` followed by `k` zero bytes, so
/// eight bytes fold into the register with eight independent lookups instead of a chain of eight
/// dependent ones (a model blob is checked on every load: 2.5 MB at about 6 ms byte by byte on the
/// host). 8 KB of tables, in flash on a target. (Indexed in a constant: an index out of range
/// would fail the build, not panic at run time.)
#[allow(clippy::indexing_slicing)]
const SLICES: [[u32; 256]; 8] = {
    let mut s = [[0u32; 256]; 8];
    let mut i = 0;
    while i < 256 {
        s[0][i] = TABLE[i];
        i += 1;
    }
    let mut k = 1;
    while k < 8 {
        let mut i = 0;
        while i < 256 {
            let prev = s[k - 1][i];
            s[k][i] = TABLE[(prev & 0xFF) as usize] ^ (prev >> 8);
            i += 1;
        }
        k += 1;
    }
    s
};

/// One byte into the register (`SLICES[0]` is the byte table, so only the slices are kept).
#[inline(always)]
fn byte(c: u32, b: u8) -> u32 {
    slice(0, c ^ b as u32) ^ (c >> 8)
}

/// `SLICES[k][b]` (`k < 8`, `b` a byte: always there).
#[inline(always)]
fn slice(k: usize, b: u32) -> u32 {
    SLICES.get(k).and_then(|t| t.get((b & 0xFF) as usize)).copied().unwrap_or(0)
}

/// CRC-32 of `data` (same as zlib's `crc32`), eight bytes a step.
pub fn crc32(data: &[u8]) -> u32 {
    let mut c = !0u32;
    let mut words = data.chunks_exact(8);
    for w in &mut words {
        let mut lo = [0u8; 4];
        let mut hi = [0u8; 4];
        lo.copy_from_slice(w.get(..4).unwrap_or(&[0; 4]));
        hi.copy_from_slice(w.get(4..).unwrap_or(&[0; 4]));
        let a = c ^ u32::from_le_bytes(lo);
        let b = u32::from_le_bytes(hi);
        c = slice(7, a) ^ slice(6, a >> 8) ^ slice(5, a >> 16) ^ slice(4, a >> 24) ^ slice(3, b) ^ slice(2, b >> 8) ^ slice(1, b >> 16) ^ slice(0, b >> 24);
    }
    for b in words.remainder() {
        c = byte(c, *b);
    }
    !c
}

#[cfg(test)]
#[allow(clippy::indexing_slicing)]
mod tests {
    #[test]
    fn known_value() {
        assert_eq!(super::crc32(b"123456789"), 0xCBF4_3926);
    }

    /// Eight bytes a step gives the byte-by-byte CRC for every length and alignment of the tail.
    #[test]
    fn slices_match_bytes() {
        let mut data = [0u8; 1000];
        for (i, d) in data.iter_mut().enumerate() {
            *d = ((i as u32).wrapping_mul(2_654_435_761) >> 13) as u8;
        }
        for start in 0..9 {
            for end in [start, start + 1, start + 7, start + 8, start + 9, 500, 999, 1000] {
                let part = &data[start..end];
                let mut c = !0u32;
                for b in part {
                    c = super::byte(c, *b);
                }
                assert_eq!(super::crc32(part), !c, "bytes {start}..{end}");
            }
        }
    }
}
