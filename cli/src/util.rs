//! Helpers shared by every subcommand: atomic output, JSON printing, range parsing.

use anyhow::{Context, Result, bail};
use std::io::Write;
use std::path::Path;

/// Writes `bytes` to `path` atomically: a temporary file in the same directory, then a rename,
/// so an interrupted run never leaves a half-written file behind.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    write_atomic_with(path, |w| w.write_all(bytes).map_err(Into::into))
}

/// Like [`write_atomic`], streaming through a writer callback.
pub fn write_atomic_with(
    path: &Path,
    f: impl FnOnce(&mut std::io::BufWriter<&mut std::fs::File>) -> Result<()>,
) -> Result<()> {
    let dir = match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    };
    std::fs::create_dir_all(dir)
        .with_context(|| format!("cannot create directory '{}'", dir.display()))?;
    let mut tmp = tempfile::NamedTempFile::new_in(dir)
        .with_context(|| format!("cannot create a temporary file in '{}'", dir.display()))?;
    {
        let mut w = std::io::BufWriter::new(tmp.as_file_mut());
        f(&mut w)?;
        w.flush()?;
    }
    tmp.persist(path)
        .with_context(|| format!("cannot write '{}'", path.display()))?;
    Ok(())
}

/// Prints a serializable value as one line of JSON on stdout.
pub fn print_json<T: serde::Serialize>(value: &T) -> Result<()> {
    println!("{}", serde_json::to_string(value)?);
    Ok(())
}

/// Parses `a:b:step` (inclusive of `b` when it lies on the grid) or a single value `a`.
/// `flag` names the parameter in the error message.
pub fn parse_range(flag: &str, text: &str) -> Result<Vec<f64>> {
    let parts: Vec<&str> = text.split(':').collect();
    let num = |s: &str| -> Result<f64> {
        let v: f64 = s
            .trim()
            .parse()
            .with_context(|| format!("{flag}: '{s}' is not a number (expected a:b:step)"))?;
        if !v.is_finite() {
            bail!("{flag}: '{s}' is not finite");
        }
        Ok(v)
    };
    match parts.as_slice() {
        [a] => Ok(vec![num(a)?]),
        [a, b, step] => {
            let (a, b, step) = (num(a)?, num(b)?, num(step)?);
            if step <= 0.0 {
                bail!("{flag}: step must be positive, got {step}");
            }
            if b < a {
                bail!("{flag}: end {b} is below start {a}");
            }
            let n = ((b - a) / step + 1e-9).floor() as usize + 1;
            if n > 100_000_000 {
                bail!("{flag}: {n} values is too many");
            }
            Ok((0..n).map(|i| a + i as f64 * step).collect())
        }
        _ => bail!("{flag}: expected a:b:step or a single value, got '{text}'"),
    }
}

/// Parses a comma-separated list of numbers; `flag` names the parameter in errors.
pub fn parse_list(flag: &str, text: &str) -> Result<Vec<f64>> {
    text.split(',')
        .map(|s| {
            let v: f64 = s
                .trim()
                .parse()
                .with_context(|| format!("{flag}: '{s}' is not a number"))?;
            if !v.is_finite() {
                bail!("{flag}: '{s}' is not finite");
            }
            Ok(v)
        })
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn range_includes_end_on_grid() {
        let v = parse_range("--depths-mm", "17:26:1.5").unwrap();
        assert_eq!(v.len(), 7);
        assert!((v[6] - 26.0).abs() < 1e-12);
        assert!(parse_range("--x", "1:0:1").is_err());
        assert!(parse_range("--x", "1:2:0").is_err());
        assert!(parse_range("--x", "a").is_err());
    }

    #[test]
    fn atomic_write_replaces_whole_file() {
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("sub/out.txt");
        write_atomic(&p, b"hello").unwrap();
        write_atomic(&p, b"bye").unwrap();
        assert_eq!(std::fs::read(&p).unwrap(), b"bye");
        assert_eq!(std::fs::read_dir(p.parent().unwrap()).unwrap().count(), 1);
    }
}
