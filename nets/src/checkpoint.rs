//! Checkpoints: a versioned binary file of every parameter and batch-norm statistic, closed
//! by an FNV-1a 64 checksum. Layout (little endian): magic "NANOEYE-NETS\0\0\0\0", u32 version,
//! u32 JSON length, the config JSON, u32 tensor count, then per tensor u32 name length, name,
//! u64 length, f32 values; finally u64 checksum of everything before it.

use crate::arch::SupernetConfig;
use crate::error::{NetsError, Result};
use crate::supernet::Supernet;
use std::path::Path;

const MAGIC: &[u8; 16] = b"NANOEYE-NETS\0\0\0\0";
/// Format version written and accepted (3: the calibration head's hidden layer reads the pooled
/// expansion and the x, y moments of the last and the stride-8 stage; 2: of the last stage
/// only; 1: the pooled expansion alone).
pub const VERSION: u32 = 3;

fn fnv1a(bytes: &[u8]) -> u64 {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    for &b in bytes {
        h ^= b as u64;
        h = h.wrapping_mul(0x0000_0100_0000_01b3);
    }
    h
}

fn tensors(net: &mut Supernet) -> Vec<(String, Vec<f32>)> {
    let mut out = Vec::new();
    net.visit(&mut |name, p| out.push((name.to_string(), p.value.clone())));
    net.visit_bn(&mut |name, bn| {
        out.push((format!("{name}.running_mean"), bn.running_mean.clone()));
        out.push((format!("{name}.running_var"), bn.running_var.clone()));
    });
    out
}

/// Serializes the supernet into checkpoint bytes.
pub fn to_bytes(net: &mut Supernet) -> Result<Vec<u8>> {
    let cfg = serde_json::to_vec(&net.config).map_err(|e| NetsError::Checkpoint(e.to_string()))?;
    let ts = tensors(net);
    // Reserved once and each tensor appended whole: appended 4 bytes at a time, the writing
    // was most of a debug-build save.
    let size = MAGIC.len()
        + 8
        + cfg.len()
        + 4
        + ts.iter()
            .map(|(n, v)| 12 + n.len() + 4 * v.len())
            .sum::<usize>()
        + 8;
    let mut b = Vec::with_capacity(size);
    b.extend_from_slice(MAGIC);
    b.extend_from_slice(&VERSION.to_le_bytes());
    b.extend_from_slice(&(cfg.len() as u32).to_le_bytes());
    b.extend_from_slice(&cfg);
    b.extend_from_slice(&(ts.len() as u32).to_le_bytes());
    for (name, v) in &ts {
        b.extend_from_slice(&(name.len() as u32).to_le_bytes());
        b.extend_from_slice(name.as_bytes());
        b.extend_from_slice(&(v.len() as u64).to_le_bytes());
        extend_f32_le(&mut b, v);
    }
    debug_assert_eq!(b.len() + 8, size);
    let h = fnv1a(&b);
    b.extend_from_slice(&h.to_le_bytes());
    Ok(b)
}

/// Appends `v` to `b` as little-endian f32s (4 bytes each), in one copy where the target is
/// little-endian: element by element, checkpoint writing was half of a debug-build training
/// step that checkpoints every step.
pub fn extend_f32_le(b: &mut Vec<u8>, v: &[f32]) {
    #[cfg(target_endian = "little")]
    {
        // SAFETY: f32 has no padding and its in-memory bytes on a little-endian target are
        // its `to_le_bytes`; the slice covers exactly `v`'s memory, read only.
        let bytes = unsafe {
            std::slice::from_raw_parts(v.as_ptr().cast::<u8>(), std::mem::size_of_val(v))
        };
        b.extend_from_slice(bytes);
    }
    #[cfg(not(target_endian = "little"))]
    for x in v {
        b.extend_from_slice(&x.to_le_bytes());
    }
}

struct Reader<'a> {
    b: &'a [u8],
    pos: usize,
}

impl Reader<'_> {
    fn take(&mut self, n: usize) -> Result<&[u8]> {
        if self.pos + n > self.b.len() {
            return Err(NetsError::Checkpoint("file truncated".into()));
        }
        let s = &self.b[self.pos..self.pos + n];
        self.pos += n;
        Ok(s)
    }
    fn u32(&mut self) -> Result<u32> {
        Ok(u32::from_le_bytes(
            self.take(4)?
                .try_into()
                .map_err(|_| NetsError::Checkpoint("bad u32".into()))?,
        ))
    }
    fn u64(&mut self) -> Result<u64> {
        Ok(u64::from_le_bytes(
            self.take(8)?
                .try_into()
                .map_err(|_| NetsError::Checkpoint("bad u64".into()))?,
        ))
    }
}

/// Loads checkpoint bytes into `net`; refuses a wrong magic, version, checksum, configuration,
/// tensor name or length, leaving `net` untouched on error.
pub fn from_bytes(net: &mut Supernet, bytes: &[u8]) -> Result<()> {
    if bytes.len() < MAGIC.len() + 8 || &bytes[..MAGIC.len()] != MAGIC {
        return Err(NetsError::Checkpoint(
            "not a nanoeye-nets checkpoint (bad magic)".into(),
        ));
    }
    let (body, tail) = bytes.split_at(bytes.len() - 8);
    let stored = u64::from_le_bytes(
        tail.try_into()
            .map_err(|_| NetsError::Checkpoint("bad checksum".into()))?,
    );
    if fnv1a(body) != stored {
        return Err(NetsError::Checkpoint(
            "checksum mismatch: the file is corrupt".into(),
        ));
    }
    let mut r = Reader {
        b: body,
        pos: MAGIC.len(),
    };
    let version = r.u32()?;
    if version != VERSION {
        return Err(NetsError::Checkpoint(format!(
            "version {version}, this build reads {VERSION}: train the run again with this build"
        )));
    }
    let n = r.u32()? as usize;
    let cfg: SupernetConfig = serde_json::from_slice(r.take(n)?)
        .map_err(|e| NetsError::Checkpoint(format!("config: {e}")))?;
    if cfg != net.config {
        return Err(NetsError::Checkpoint(format!(
            "config {cfg:?} does not match the network's {:?}",
            net.config
        )));
    }
    let expected = tensors(net);
    let count = r.u32()? as usize;
    if count != expected.len() {
        return Err(NetsError::Checkpoint(format!(
            "{count} tensors, the network has {}",
            expected.len()
        )));
    }
    let mut loaded = Vec::with_capacity(count);
    for (name, v) in &expected {
        let ln = r.u32()? as usize;
        let got = String::from_utf8_lossy(r.take(ln)?).into_owned();
        let len = r.u64()? as usize;
        if &got != name || len != v.len() {
            return Err(NetsError::Checkpoint(format!(
                "tensor '{got}' of length {len} where '{name}' of length {} was expected",
                v.len()
            )));
        }
        let raw = r.take(
            len.checked_mul(4)
                .ok_or_else(|| NetsError::Checkpoint("length overflow".into()))?,
        )?;
        let v: Vec<f32> = raw
            .chunks_exact(4)
            .map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]]))
            .collect();
        // A checksum vouches for the bytes, not for the training that wrote them: a diverged
        // one leaves NaN weights, which would answer every frame with NaN.
        if let Some(i) = v.iter().position(|x| !x.is_finite()) {
            return Err(NetsError::Checkpoint(format!(
                "tensor '{name}' holds a non-finite value ({}) at index {i}: the training that \
                 wrote it diverged; train again with lower learning rates",
                v[i]
            )));
        }
        if name.ends_with(".running_var")
            && let Some(i) = v.iter().position(|&x| x < 0.0)
        {
            return Err(NetsError::Checkpoint(format!(
                "tensor '{name}' holds the negative variance {} at index {i}",
                v[i]
            )));
        }
        loaded.push(v);
    }
    let mut it = loaded.into_iter();
    net.visit(&mut |_, p| {
        if let Some(v) = it.next() {
            p.value = v;
        }
    });
    net.visit_bn(&mut |_, bn| {
        if let (Some(m), Some(v)) = (it.next(), it.next()) {
            bn.running_mean = m;
            bn.running_var = v;
        }
    });
    Ok(())
}

/// Writes a checkpoint atomically (temporary file, then rename).
pub fn save(net: &mut Supernet, path: &Path) -> Result<()> {
    let bytes = to_bytes(net)?;
    let dir = path
        .parent()
        .filter(|p| !p.as_os_str().is_empty())
        .unwrap_or(Path::new("."));
    let tmp = dir.join(format!(
        ".{}.tmp",
        path.file_name().and_then(|s| s.to_str()).unwrap_or("ckpt")
    ));
    std::fs::write(&tmp, &bytes)?;
    std::fs::rename(&tmp, path)?;
    Ok(())
}

/// Reads a checkpoint file into `net`.
pub fn load(net: &mut Supernet, path: &Path) -> Result<()> {
    let bytes = std::fs::read(path)?;
    from_bytes(net, &bytes)
}
