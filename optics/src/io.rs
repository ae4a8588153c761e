//! NPY input/output: free-form phase maps in, PSF stacks out ([depth, y, x], float32).

use crate::error::{OpticsError, Result};
use crate::psf::PsfStack;
use faer::Mat;
use npyz::WriterBuilder;
use std::io::Write;
use std::path::Path;

fn io_err(path: &Path, source: std::io::Error) -> OpticsError {
    OpticsError::Io {
        path: path.display().to_string(),
        cause: source,
    }
}

fn fmt_err(path: &Path, reason: impl Into<String>) -> OpticsError {
    OpticsError::Format {
        path: path.display().to_string(),
        reason: reason.into(),
    }
}

/// Reads a 2-D square float32/float64 NPY array (C or Fortran order) as a phase map (rad).
pub fn read_phase_npy(path: &Path) -> Result<Mat<f64>> {
    // A device or a FIFO (`/dev/zero`) would be read until memory ran out; a phase map is at
    // most 20000² f64 (the aperture grid's bound) plus its header.
    let meta = std::fs::metadata(path).map_err(|e| io_err(path, e))?;
    if !meta.is_file() {
        return Err(fmt_err(path, "not a regular file"));
    }
    const MAX_BYTES: u64 = 20_000 * 20_000 * 8 + (1 << 16);
    if meta.len() > MAX_BYTES {
        return Err(fmt_err(
            path,
            format!("{} bytes, more than a phase map's {MAX_BYTES}", meta.len()),
        ));
    }
    let bytes = std::fs::read(path).map_err(|e| io_err(path, e))?;
    // npyz allocates the header length it reads and multiplies the dimensions unchecked
    // (2³²×2³² overflowed inside it).
    let dims = nanoeye_npy::check(&bytes, bytes.len() as u64).map_err(|why| fmt_err(path, why))?;
    if let Some(d) = dims.filter(|d| d.iter().any(|&v| v > 20_000)) {
        return Err(fmt_err(
            path,
            format!("shape {d:?}: larger than the aperture grid's 20000²"),
        ));
    }
    let npy = npyz::NpyFile::new(&bytes[..]).map_err(|e| fmt_err(path, e.to_string()))?;
    let shape = npy.shape().to_vec();
    if shape.len() != 2 || shape[0] != shape[1] || shape[0] == 0 {
        return Err(fmt_err(
            path,
            format!("expected a square 2-D array, got shape {shape:?}"),
        ));
    }
    // The header alone can claim any shape: 2³²×2³² overflowed n·n (a panic building the map).
    if shape[0] > 20_000 {
        return Err(fmt_err(
            path,
            format!(
                "a {0}×{0} phase map is larger than the aperture grid's 20000²",
                shape[0]
            ),
        ));
    }
    let n = shape[0] as usize;
    let fortran = npy.order() == npyz::Order::Fortran;
    let descr = npy.dtype().descr();
    let data: Vec<f64> = if descr.contains("f8") {
        npy.into_vec::<f64>()
            .map_err(|e| fmt_err(path, e.to_string()))?
    } else if descr.contains("f4") {
        let v = npy
            .into_vec::<f32>()
            .map_err(|e| fmt_err(path, e.to_string()))?;
        v.into_iter().map(f64::from).collect()
    } else {
        return Err(fmt_err(
            path,
            format!("dtype {descr} is not float32/float64"),
        ));
    };
    if data.len() != n * n {
        return Err(fmt_err(
            path,
            format!("{} values for a {n}×{n} map", data.len()),
        ));
    }
    if data.iter().any(|v| !v.is_finite()) {
        return Err(fmt_err(path, "phase map holds non-finite values"));
    }
    Ok(Mat::from_fn(n, n, |i, j| {
        if fortran {
            data[j * n + i]
        } else {
            data[i * n + j]
        }
    }))
}

/// Writes the stack's planes as one float32 NPY array [depth, y, x] to `w`.
pub fn write_stack_npy<W: Write>(stack: &PsfStack, w: W) -> std::io::Result<()> {
    let (nz, ny, nx) = (
        stack.planes.len(),
        stack.planes.first().map_or(0, |m| m.nrows()),
        stack.planes.first().map_or(0, |m| m.ncols()),
    );
    let mut wr = npyz::WriteOptions::new()
        .default_dtype()
        .shape(&[nz as u64, ny as u64, nx as u64])
        .writer(w)
        .begin_nd()?;
    for p in &stack.planes {
        for i in 0..ny {
            for j in 0..nx {
                wr.push(&p[(i, j)])?;
            }
        }
    }
    wr.finish()
}

/// Writes the stack to `path` atomically (temporary file in the same directory, then rename).
pub fn save_stack_npy(stack: &PsfStack, path: &Path) -> Result<()> {
    // Renaming over a symlink, pipe, device or directory would replace that node silently.
    if let Ok(m) = std::fs::symlink_metadata(path)
        && !m.file_type().is_file()
    {
        return Err(io_err(
            path,
            std::io::Error::other("exists and is not a regular file; refusing to replace it"),
        ));
    }
    let dir = match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p,
        _ => Path::new("."),
    };
    // Named `.nanoeye-tmp-<pid>-…`: the CLI removes those a killed process left behind.
    let mut b = tempfile::Builder::new();
    // A temporary file is created owner-only (0600); an output is an ordinary file, so ask
    // for 0666 and let the umask take its share, as `File::create` would.
    #[cfg(unix)]
    b.permissions(std::os::unix::fs::PermissionsExt::from_mode(0o666));
    let mut tmp = b
        .prefix(&format!(".nanoeye-tmp-{}-", std::process::id()))
        .tempfile_in(dir)
        .map_err(|e| io_err(path, e))?;
    {
        let mut bw = std::io::BufWriter::new(tmp.as_file_mut());
        write_stack_npy(stack, &mut bw).map_err(|e| io_err(path, e))?;
        bw.flush().map_err(|e| io_err(path, e))?;
    }
    tmp.persist(path).map_err(|e| io_err(path, e.error))?;
    Ok(())
}
