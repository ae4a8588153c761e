//! An NPY file's preamble checked before a parser trusts it.
//!
//! npyz reads the header length and allocates it (a 27-byte file claiming a 4 GiB header
//! aborted the process: `memory allocation of 4294967280 bytes failed`) and multiplies the
//! shape's dimensions in u64 unchecked (2³²×2³² panicked in a debug build and wrapped to an
//! empty array in a release one). [`check`] reads what the preamble claims from the file's
//! first bytes and refuses a claim the file's length cannot hold; every NPY reader of the
//! workspace calls it first. No dependency: the stage crates that read NPY (metalib, optics,
//! datagen) and the CLI share it without depending on one another.

/// Bytes of a file [`check`] wants to see: the largest header it reads plus the preamble.
pub const PREFIX_BYTES: usize = (1 << 16) + 12;

/// The dimensions an NPY header's `'shape'` tuple claims, parsed from the file's first bytes
/// without trusting them; `None` when there is no shape tuple to read (the parser then reports
/// the malformed header).
pub fn header_dims(bytes: &[u8]) -> Option<Vec<u128>> {
    let head = &bytes[..bytes.len().min(PREFIX_BYTES)];
    let text = String::from_utf8_lossy(head);
    let at = text.find("'shape'")?;
    let rest = &text[at..];
    let rest = &rest[rest.find('(')? + 1..];
    let tuple = &rest[..rest.find(')')?];
    tuple
        .split(',')
        .map(str::trim)
        .filter(|t| !t.is_empty())
        .map(|t| t.trim_end_matches('L').parse::<u128>().ok())
        .collect()
}

/// What an NPY preamble claims about its data.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Claim {
    /// The shape's dimensions.
    pub dims: Vec<u128>,
    /// Bytes per value (of a plain `'descr'`; 1 where it has no size).
    pub item_bytes: u128,
    /// Whether `item_bytes` is the dtype's own size (a plain `'descr'`), so that the data's
    /// length must equal what the shape needs.
    pub sized: bool,
    /// Bytes of the file after the header.
    pub data_bytes: u128,
}

impl Claim {
    /// Bytes the shape's values need; None past u128.
    pub fn needs(&self) -> Option<u128> {
        self.dims
            .iter()
            .try_fold(self.item_bytes, |n, &d| n.checked_mul(d))
    }

    /// Whether the data after the header holds every value the shape claims.
    pub fn fits(&self) -> bool {
        self.needs().is_some_and(|n| n <= self.data_bytes)
    }
}

/// Reads what the preamble in `prefix` (the file's first bytes, at least [`PREFIX_BYTES`] of
/// them or the whole file) claims, refusing a header that ends beyond `file_len`, the file's
/// length in bytes. None where the header has no readable shape, or `prefix` is not an NPY
/// preamble (the parser names that better). A file cut short is a claim that does not
/// [`Claim::fits`]: a stream reader may still read what is there.
pub fn claim(prefix: &[u8], file_len: u64) -> Result<Option<Claim>, String> {
    if prefix.len() < 10 || !prefix.starts_with(b"\x93NUMPY") {
        return Ok(None);
    }
    // Version 1 has a u16 header length at byte 8; versions 2 and 3 a u32.
    let (start, header_len) = match prefix[6] {
        1 => (10u64, u64::from(u16::from_le_bytes([prefix[8], prefix[9]]))),
        _ if prefix.len() >= 12 => (
            12,
            u64::from(u32::from_le_bytes([
                prefix[8], prefix[9], prefix[10], prefix[11],
            ])),
        ),
        _ => return Ok(None),
    };
    let data_at = start + header_len;
    if data_at > file_len {
        return Err(format!(
            "the header claims {header_len} bytes, beyond the file's {file_len}"
        ));
    }
    let item = item_bytes(prefix);
    Ok(header_dims(prefix).map(|dims| Claim {
        dims,
        item_bytes: item.unwrap_or(1),
        sized: item.is_some(),
        data_bytes: u128::from(file_len - data_at),
    }))
}

/// [`claim`], also refusing a shape whose values the data after the header cannot hold, or
/// (for a plain dtype) data longer than the shape's values: returns the claimed dimensions
/// (None where there is no readable shape) or why the file cannot be what it claims.
pub fn check(prefix: &[u8], file_len: u64) -> Result<Option<Vec<u128>>, String> {
    filled(claim(prefix, file_len)?)
}

/// The claim's dimensions, or why its data cannot hold them.
fn filled(c: Option<Claim>) -> Result<Option<Vec<u128>>, String> {
    match c {
        Some(c) if !c.fits() => Err(format!(
            "shape {:?} of {}-byte values needs more than the file's {} bytes of data",
            c.dims, c.item_bytes, c.data_bytes
        )),
        // Bytes past the shape's values: the header does not describe the data (a 200×200
        // f8 map under a (100, 100) header was read as its first quarter, exit 0; a helper's
        // audit). A stream reader that wants a file cut short uses `claim` instead.
        Some(c) if c.sized && c.needs().is_some_and(|n| n < c.data_bytes) => Err(format!(
            "shape {:?} of {}-byte values needs {} bytes of data, but the file holds {} after \
             its header: the header does not describe the data",
            c.dims,
            c.item_bytes,
            c.needs().unwrap_or(0),
            c.data_bytes
        )),
        c => Ok(c.map(|c| c.dims)),
    }
}

/// Bytes per value of a plain `'descr'` (`'<f4'` 4, `'<c16'` 16), from the header text; None
/// for a structured dtype or one without a size.
fn item_bytes(prefix: &[u8]) -> Option<u128> {
    let text = String::from_utf8_lossy(&prefix[..prefix.len().min(PREFIX_BYTES)]);
    let rest = &text[text.find("'descr'")? + "'descr'".len()..];
    let rest = rest
        .trim_start()
        .strip_prefix(':')?
        .trim_start()
        .strip_prefix('\'')?;
    let descr = &rest[..rest.find('\'')?];
    // A unicode string's digits count characters of four bytes each, not bytes.
    if descr.contains('U') {
        return None;
    }
    let digits: String = descr.chars().skip_while(|c| !c.is_ascii_digit()).collect();
    digits.parse().ok().filter(|&n| n > 0)
}

/// [`claim`] on the file at `path`: reads its first [`PREFIX_BYTES`] and its length. Call it
/// on a regular file (a FIFO's read would block).
pub fn claim_file(path: &std::path::Path) -> std::io::Result<Result<Option<Claim>, String>> {
    use std::io::Read;
    let mut f = std::fs::File::open(path)?;
    let len = f.metadata()?.len();
    let mut prefix = Vec::with_capacity(PREFIX_BYTES);
    f.by_ref()
        .take(PREFIX_BYTES as u64)
        .read_to_end(&mut prefix)?;
    Ok(claim(&prefix, len))
}

/// [`check`] on the file at `path` (as [`claim_file`] reads it).
pub fn check_file(path: &std::path::Path) -> std::io::Result<Result<Option<Vec<u128>>, String>> {
    Ok(claim_file(path)?.and_then(filled))
}

#[cfg(test)]
mod tests {
    use super::*;

    /// An NPY file of version `major` whose header text is `dict` and that holds `data` bytes.
    fn npy(major: u8, dict: &str, data: usize) -> Vec<u8> {
        let start = if major == 1 { 10 } else { 12 };
        let pad = (64 - (start + dict.len() + 1) % 64) % 64;
        let head = format!("{dict}{}\n", " ".repeat(pad));
        let mut b = b"\x93NUMPY".to_vec();
        b.extend([major, 0]);
        match major {
            1 => b.extend((head.len() as u16).to_le_bytes()),
            _ => b.extend((head.len() as u32).to_le_bytes()),
        }
        b.extend(head.as_bytes());
        b.extend(vec![0u8; data]);
        b
    }

    fn dict(shape: &str) -> String {
        format!("{{'descr': '<f4', 'fortran_order': False, 'shape': {shape}, }}")
    }

    #[test]
    fn an_honest_file_passes_with_its_dimensions() {
        for major in [1, 2, 3] {
            let b = npy(major, &dict("(3, 4)"), 48);
            assert_eq!(check(&b, b.len() as u64), Ok(Some(vec![3, 4])));
            // A scalar and an empty array claim one and zero values.
            let b = npy(major, &dict("()"), 4);
            assert_eq!(check(&b, b.len() as u64), Ok(Some(vec![])));
            let b = npy(major, &dict("(0, 7)"), 0);
            assert_eq!(check(&b, b.len() as u64), Ok(Some(vec![0, 7])));
        }
    }

    #[test]
    fn claims_the_file_cannot_hold_are_refused() {
        // A version-2 header claiming 0xFFFFFFF0 bytes in a 27-byte file (npyz allocated it).
        let mut b = b"\x93NUMPY\x02\x00".to_vec();
        b.extend(0xFFFF_FFF0u32.to_le_bytes());
        b.extend(b"{'descr': '<f4'");
        assert_eq!(b.len(), 27);
        let e = check(&b, 27).unwrap_err();
        assert!(e.contains("4294967280") && e.contains("27"), "{e}");
        // 2³² × 2³² values (wrapped to 0 in u64), and a shape one value beyond the data.
        let b = npy(1, &dict("(4294967296, 4294967296)"), 64);
        assert!(check(&b, b.len() as u64).is_err());
        let b = npy(1, &dict("(2, 3)"), 5);
        assert!(check(&b, b.len() as u64).is_err());
        // Data past the shape's values (one byte more, or f8 data under an f4 header).
        for data in [25, 48] {
            let b = npy(1, &dict("(2, 3)"), data);
            let e = check(&b, b.len() as u64).unwrap_err();
            assert!(e.contains("does not describe") && e.contains("24"), "{e}");
        }
        // Dimensions past u128 do not parse: no shape, left to the parser.
        let b = npy(1, &dict("(340282366920938463463374607431768211456, 2)"), 8);
        assert_eq!(check(&b, b.len() as u64), Ok(None));
        // The file's length, not the prefix's, bounds the data.
        let b = npy(1, &dict("(1000,)"), 4000);
        assert!(check(&b[..200], 200).is_err());
        assert_eq!(check(&b[..200], b.len() as u64), Ok(Some(vec![1000])));
    }

    #[test]
    fn what_is_not_an_npy_preamble_is_left_to_the_parser() {
        assert_eq!(check(b"", 0), Ok(None));
        assert_eq!(check(b"PK\x03\x04 not npy at all", 20), Ok(None));
        assert_eq!(check(b"\x93NUMPY\x02\x00\x10\x00", 10), Ok(None));
        let b = npy(1, "{'descr': '<f4', 'fortran_order': False}", 0);
        assert_eq!(check(&b, b.len() as u64), Ok(None));
    }

    #[test]
    fn check_file_reads_the_prefix_and_the_length() {
        let d = std::env::temp_dir().join(format!("nanoeye-npy-{}", std::process::id()));
        std::fs::create_dir_all(&d).unwrap();
        let p = d.join("a.npy");
        std::fs::write(&p, npy(1, &dict("(2, 2)"), 16)).unwrap();
        assert_eq!(check_file(&p).unwrap(), Ok(Some(vec![2, 2])));
        std::fs::write(&p, npy(1, &dict("(2, 2)"), 15)).unwrap();
        assert!(check_file(&p).unwrap().is_err());
        std::fs::write(&p, npy(1, &dict("(2, 2)"), 17)).unwrap();
        assert!(check_file(&p).unwrap().is_err());
        // A structured dtype has no plain size: its length is left to the parser.
        let structured = "{'descr': [('a', '<f4')], 'fortran_order': False, 'shape': (2,), }";
        std::fs::write(&p, npy(1, structured, 9)).unwrap();
        assert_eq!(check_file(&p).unwrap(), Ok(Some(vec![2])));
        std::fs::remove_dir_all(&d).unwrap();
    }
}
