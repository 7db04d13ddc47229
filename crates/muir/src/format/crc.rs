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

/// CRC-32 of `data` (same as zlib's `crc32`).
pub fn crc32(data: &[u8]) -> u32 {
    let mut c = !0u32;
    for b in data {
        // The index is a byte: the table (256 entries) always has it.
        c = TABLE.get(((c ^ *b as u32) & 0xFF) as usize).copied().unwrap_or(0) ^ (c >> 8);
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
}
