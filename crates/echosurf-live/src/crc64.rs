//! CRC-64 as OpenIGTLink uses it: ECMA-182 polynomial 0x42F0E1EBA9EA3693, initial value 0, not
//! reflected, no final xor (the check value of "123456789" is 0x6C40DF5F0B497347).

/// The ECMA-182 generator polynomial (without its x^64 term).
pub const POLYNOMIAL: u64 = 0x42F0_E1EB_A9EA_3693;

const TABLE: [u64; 256] = make_table();

const fn make_table() -> [u64; 256] {
    let mut table = [0u64; 256];
    let mut i = 0;
    while i < 256 {
        let mut crc = (i as u64) << 56;
        let mut bit = 0;
        while bit < 8 {
            crc = if crc & (1 << 63) != 0 {
                (crc << 1) ^ POLYNOMIAL
            } else {
                crc << 1
            };
            bit += 1;
        }
        table[i] = crc;
        i += 1;
    }
    table
}

/// The CRC-64 of `bytes`.
pub fn crc64(bytes: &[u8]) -> u64 {
    bytes.iter().fold(0u64, |crc, &b| {
        TABLE[(((crc >> 56) as u8) ^ b) as usize] ^ (crc << 8)
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn check_value_of_the_ecma_182_crc() {
        assert_eq!(crc64(b"123456789"), 0x6C40_DF5F_0B49_7347);
        assert_eq!(crc64(b""), 0);
    }

    /// The table-driven CRC against the bit-by-bit definition (polynomial division) on random bytes.
    #[test]
    fn table_matches_bitwise_division() {
        fn bitwise(bytes: &[u8]) -> u64 {
            let mut crc = 0u64;
            for &b in bytes {
                crc ^= (b as u64) << 56;
                for _ in 0..8 {
                    crc = if crc & (1 << 63) != 0 {
                        (crc << 1) ^ POLYNOMIAL
                    } else {
                        crc << 1
                    };
                }
            }
            crc
        }
        let bytes: Vec<u8> = (0..1000u32)
            .map(|i| (i.wrapping_mul(2_654_435_761) >> 13) as u8)
            .collect();
        for len in [1, 7, 64, 999] {
            assert_eq!(crc64(&bytes[..len]), bitwise(&bytes[..len]));
        }
    }
}
