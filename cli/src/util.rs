//! Helpers shared by every subcommand: atomic output, JSON printing, range parsing.

use anyhow::{Context, Result, bail};
use std::io::Write;
use std::path::{Path, PathBuf};

/// Prefix of every temporary file the atomic writers create: `.nanoeye-tmp-<pid>-XXXXXX`.
/// A run killed between create and rename leaves one behind; the next write into the same
/// directory removes those whose process is gone ([`remove_stale_temps`]).
pub const TMP_PREFIX: &str = ".nanoeye-tmp-";

/// Writes `bytes` to `path` atomically: a temporary file in the same directory, then a rename,
/// so an interrupted run never leaves a half-written file behind.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<()> {
    write_atomic_with(path, |w| w.write_all(bytes).map_err(Into::into))
}

/// Fails unless `path` is absent or a regular file, and where its spelling names a directory
/// (`out/`, `.`, `a/..`): renaming over a symlink, pipe, device or directory would silently
/// replace that node with a plain file.
pub fn check_output_target(path: &Path) -> Result<()> {
    // `out/`, `.` or `a/..` name a directory: the write failed only at its end, after the
    // work (`search pareto --plot Q/` scored every subnet first; a helper's audit).
    let text = path.as_os_str().as_encoded_bytes();
    if text.ends_with(b"/") || text.ends_with(b"/.") || text == b"." || path.file_name().is_none() {
        bail!(
            "'{}' names a directory, not a file; give a file name",
            path.display()
        );
    }
    match std::fs::symlink_metadata(path) {
        Ok(m) if m.file_type().is_file() => Ok(()),
        Ok(m) => {
            let ft = m.file_type();
            let what = if ft.is_symlink() {
                "a symbolic link"
            } else if ft.is_dir() {
                "a directory"
            } else {
                "a pipe, socket or device"
            };
            bail!(
                "'{}' exists and is {what}, not a regular file; refusing to replace it",
                path.display()
            )
        }
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(()),
        Err(e) => Err(e).with_context(|| format!("cannot inspect '{}'", path.display())),
    }
}

/// Where `given` (a JSON document) has something other than an object at a place `template`
/// (the same type's serialization) has one, that place as a path (`camera`, `stages/0`), with
/// what was found: serde reads a struct from an array of its fields in order, so `[0.012, …]`
/// made a rig and `[[160,100],null,[0,0,0]]` a gaze query. A null is left to the type (an
/// optional part); keys `template` lacks are not looked at.
pub fn array_for_object(template: &serde_json::Value, given: &serde_json::Value) -> Option<String> {
    use serde_json::Value;
    fn walk(t: &Value, g: &Value, at: &str) -> Option<String> {
        let kind = |g: &Value| match g {
            Value::Array(_) => "an array",
            Value::String(_) => "a string",
            Value::Number(_) => "a number",
            Value::Bool(_) => "a boolean",
            _ => "something else",
        };
        let join = |k: &str| {
            if at.is_empty() {
                k.to_string()
            } else {
                format!("{at}/{k}")
            }
        };
        match (t, g) {
            (_, Value::Null) => None,
            (Value::Object(tm), Value::Object(gm)) => tm
                .iter()
                .find_map(|(k, tv)| gm.get(k).and_then(|gv| walk(tv, gv, &join(k)))),
            (Value::Object(_), g) if at.is_empty() => Some(format!(
                "a JSON object {{\"key\": value, …}} is expected, not {}",
                kind(g)
            )),
            (Value::Object(_), g) => Some(format!(
                "{at}: a JSON object {{\"key\": value, …}} is expected here, not {}",
                kind(g)
            )),
            (Value::Array(ta), Value::Array(ga)) if !ta.is_empty() => ga
                .iter()
                .enumerate()
                .find_map(|(i, gv)| walk(ta.get(i).unwrap_or(&ta[0]), gv, &join(&i.to_string()))),
            _ => None,
        }
    }
    walk(template, given, "")
}

/// The first value of `given` (a JSON document for `T`) that `T` does not take, as its path
/// (`camera.cx_px`) and serde's error for it alone over `template`'s other values: serde's
/// error for the whole document named a line and column only (`"cx_px": null`), or called an
/// array one element too long "trailing characters" (`"kappa_rad": [0, 0, 0]`).
pub fn failing_path<T>(template: &T, given: &serde_json::Value) -> Option<(String, String)>
where
    T: serde::Serialize + serde::de::DeserializeOwned,
{
    use serde_json::Value;
    fn leaves(v: &Value, at: String, out: &mut Vec<String>) {
        match v {
            Value::Object(m) if !m.is_empty() => {
                for (k, x) in m {
                    leaves(x, format!("{at}/{k}"), out);
                }
            }
            _ => out.push(at),
        }
    }
    let base = serde_json::to_value(template).ok()?;
    let mut paths = Vec::new();
    leaves(given, String::new(), &mut paths);
    paths.into_iter().find_map(|p| {
        let (parent, key) = p.rsplit_once('/')?;
        let mut t = base.clone();
        t.pointer_mut(parent)?
            .as_object_mut()?
            .insert(key.to_string(), given.pointer(&p)?.clone());
        let e = serde_json::from_value::<T>(t).err()?;
        Some((p.trim_start_matches('/').replace('/', "."), e.to_string()))
    })
}

/// Refuses an Arch JSON `text` laid out otherwise than an Arch (an array of its fields); text
/// that is no JSON is left to the parser's own message.
pub fn arch_layout(text: &str) -> Result<()> {
    if let Ok(v) = serde_json::from_str::<serde_json::Value>(text) {
        let t = serde_json::to_value(nanoeye_nets::Arch::min())?;
        if let Some(m) = array_for_object(&t, &v) {
            bail!("{m}");
        }
    }
    Ok(())
}

/// Removes `TMP_PREFIX` files in `dir` left by processes that no longer run (on systems
/// without /proc: those older than a day). Errors are ignored: cleaning is best effort.
pub fn remove_stale_temps(dir: &Path) {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return;
    };
    let proc = Path::new("/proc");
    let have_proc = proc.join("self").exists();
    for e in entries.flatten() {
        let name = e.file_name();
        let Some(rest) = name.to_str().and_then(|n| n.strip_prefix(TMP_PREFIX)) else {
            continue;
        };
        let Ok(meta) = e.metadata() else { continue };
        if !meta.is_file() {
            continue;
        }
        let pid = rest.split('-').next().unwrap_or("");
        let stale = if have_proc && !pid.is_empty() && pid.bytes().all(|b| b.is_ascii_digit()) {
            pid != std::process::id().to_string() && !proc.join(pid).exists()
        } else {
            meta.modified()
                .ok()
                .and_then(|t| t.elapsed().ok())
                .is_some_and(|age| age.as_secs() > 86_400)
        };
        if stale {
            let _ = std::fs::remove_file(e.path());
        }
    }
}

/// [`remove_stale_temps`] in `dir` and in every directory below it (symbolic links are not
/// followed): what a killed job left in its output tree, also in directories only the stage
/// crates write (their atomic writers use the same `.nanoeye-tmp-<pid>-` names). A resumable
/// job calls it before it resumes. Skipped under MPI, where another host's process ids mean
/// nothing here.
pub fn remove_stale_temps_under(dir: &Path) {
    if crate::dist::world().is_distributed() {
        return;
    }
    remove_stale_temps(dir);
    let Ok(entries) = std::fs::read_dir(dir) else {
        return;
    };
    for e in entries.flatten() {
        if e.file_type().is_ok_and(|t| t.is_dir()) {
            remove_stale_temps_under(&e.path());
        }
    }
}

/// Like [`write_atomic`], streaming through a writer callback.
pub fn write_atomic_with(
    path: &Path,
    f: impl FnOnce(&mut std::io::BufWriter<&mut std::fs::File>) -> Result<()>,
) -> Result<()> {
    let mut file = AtomicFile::create(path)?;
    {
        let mut w = std::io::BufWriter::new(file.tmp.as_file_mut());
        f(&mut w)?;
        w.flush()?;
    }
    file.commit()
}

/// A file written in several steps that appears at its path only once [`Self::commit`]ted:
/// until then the path is untouched, and a file dropped uncommitted (an error on the way)
/// leaves no trace.
pub struct AtomicFile {
    tmp: tempfile::NamedTempFile,
    path: PathBuf,
}

impl AtomicFile {
    /// A temporary file beside `path` (its directory created), after the checks of
    /// [`write_atomic`].
    pub fn create(path: &Path) -> Result<Self> {
        let dir = match path.parent() {
            Some(p) if !p.as_os_str().is_empty() => p,
            _ => Path::new("."),
        };
        check_output_target(path)?;
        std::fs::create_dir_all(dir)
            .with_context(|| format!("cannot create directory '{}'", dir.display()))?;
        remove_stale_temps(dir);
        let mut b = tempfile::Builder::new();
        // A temporary file is created owner-only (0600); an output is an ordinary file, so
        // ask for 0666 and let the umask take its share, as `File::create` would.
        #[cfg(unix)]
        b.permissions(std::os::unix::fs::PermissionsExt::from_mode(0o666));
        let tmp = b
            .prefix(&format!("{TMP_PREFIX}{}-", std::process::id()))
            .tempfile_in(dir)
            .with_context(|| format!("cannot create a temporary file in '{}'", dir.display()))?;
        Ok(Self {
            tmp,
            path: path.to_path_buf(),
        })
    }

    /// A buffered writer appending to the temporary file (flush it before [`Self::commit`]).
    pub fn writer(&mut self) -> std::io::BufWriter<&mut std::fs::File> {
        std::io::BufWriter::with_capacity(1 << 20, self.tmp.as_file_mut())
    }

    /// Moves the finished file into place.
    pub fn commit(self) -> Result<()> {
        let path = self.path;
        self.tmp
            .persist(&path)
            .with_context(|| format!("cannot write '{}'", path.display()))?;
        Ok(())
    }
}

/// FNV-1a (64-bit) digest of bytes and files: tells whether an input changed between a run
/// and its resume (not a cryptographic hash).
#[derive(Clone, Copy, Debug)]
pub struct Digest(u64);

impl Default for Digest {
    fn default() -> Self {
        Digest(0xcbf2_9ce4_8422_2325)
    }
}

impl Digest {
    /// Adds `bytes`.
    pub fn bytes(&mut self, bytes: &[u8]) {
        for &b in bytes {
            self.0 = (self.0 ^ u64::from(b)).wrapping_mul(0x0000_0100_0000_01b3);
        }
    }

    /// Adds the contents of the file at `path`; returns its length (bytes).
    pub fn file(&mut self, path: &Path) -> Result<u64> {
        use std::io::Read;
        let mut f = std::fs::File::open(path)
            .with_context(|| format!("cannot read '{}'", path.display()))?;
        let mut buf = vec![0u8; 1 << 20];
        let mut n = 0u64;
        loop {
            let got = f
                .read(&mut buf)
                .with_context(|| format!("cannot read '{}'", path.display()))?;
            if got == 0 {
                return Ok(n);
            }
            self.bytes(&buf[..got]);
            n += got as u64;
        }
    }

    /// The digest as 16 hexadecimal digits.
    pub fn hex(&self) -> String {
        format!("{:016x}", self.0)
    }
}

/// The identity of a rendered dataset for a resume check: the digest of its records
/// (dataset.json and frames.jsonl), not its path, so that a copy of it resumes and other
/// frames do not.
pub fn dataset_digest(flag: &str, dir: &Path) -> Result<String> {
    let mut d = Digest::default();
    for f in ["dataset.json", "frames.jsonl"] {
        d.file(&dir.join(f))
            .with_context(|| format!("{flag} {}", dir.display()))?;
    }
    Ok(d.hex())
}

/// Refuses to resume a run whose inputs `now` (a JSON object) differ from those recorded in
/// `path` when it started, naming the flag of the first key of `keys` (key, flag) that
/// differs; keys the record lacks (a run begun before they were recorded) are not compared.
/// Without a record there is nothing to compare. `out` is the flag naming the run directory.
pub fn check_inputs(
    path: &Path,
    now: &serde_json::Value,
    keys: &[(&str, &str)],
    out: &str,
) -> Result<()> {
    if let Some((flag, key, old, new)) =
        recorded_difference(path, now, keys, &format!("{out} (resume)"))?
    {
        bail!(
            "{flag}: differs from the run being resumed ({} records {key} = {old}, this \
             command gives {new}); use the original value or another {out}",
            path.display()
        );
    }
    Ok(())
}

/// The first of `keys` (key, flag) whose value in the record at `path` differs from `now`'s,
/// as (flag, key, recorded, now); keys the record lacks and a missing record are not compared.
/// `what` names the flag behind `path` in the error of a record that is not JSON.
pub fn recorded_difference<'k>(
    path: &Path,
    now: &serde_json::Value,
    keys: &[(&'k str, &'k str)],
    what: &str,
) -> Result<Option<(&'k str, &'k str, serde_json::Value, serde_json::Value)>> {
    let Some(text) = read_record(path, MAX_RECORD_BYTES).with_context(|| what.to_string())? else {
        return Ok(None);
    };
    let had: serde_json::Value = serde_json::from_str(&text)
        .with_context(|| format!("{what}: {} is not JSON", path.display()))?;
    // An array (or null, or a number) has no keys, so nothing would be compared and any
    // inputs would resume (`fisher init` mixed two window sizes; a helper's audit).
    if !had.is_object() {
        bail!(
            "{what}: {} is not a JSON object of the run's inputs; restore it or use another \
             directory",
            path.display()
        );
    }
    Ok(value_difference(&had, now, keys))
}

/// The first of `keys` (key, flag) whose value in the record `had` differs from `now`'s, as
/// (flag, key, recorded, now); keys the record lacks are not compared.
pub fn value_difference<'k>(
    had: &serde_json::Value,
    now: &serde_json::Value,
    keys: &[(&'k str, &'k str)],
) -> Option<(&'k str, &'k str, serde_json::Value, serde_json::Value)> {
    keys.iter().find_map(|&(key, flag)| {
        let old = had.get(key)?;
        (*old != now[key]).then(|| (flag, key, old.clone(), now[key].clone()))
    })
}

/// One line of JSONL input as text: `raw` without its line ending; line 1 loses a leading
/// UTF-8 byte-order mark. Fails (naming the byte offset) when the line is not UTF-8, so the
/// caller can report that one line and go on.
pub fn jsonl_line(raw: &[u8], line_no: usize) -> Result<&str> {
    let mut b = raw.strip_suffix(b"\n").unwrap_or(raw);
    b = b.strip_suffix(b"\r").unwrap_or(b);
    if line_no == 1 {
        b = b.strip_prefix(b"\xEF\xBB\xBF").unwrap_or(b);
    }
    std::str::from_utf8(b).map_err(|e| {
        anyhow::anyhow!(
            "not valid UTF-8 (invalid byte at offset {})",
            e.valid_up_to()
        )
    })
}

/// The path (`key.sub[2]`) of the first null in `v`, depth first, skipping the top-level keys in
/// `optional`: serde_json writes a non-finite f64 as null, so a null where a number belongs is a
/// NaN or an infinity that reached an output.
pub fn first_null(v: &serde_json::Value, optional: &[&str]) -> Option<String> {
    fn walk(v: &serde_json::Value, path: String) -> Option<String> {
        match v {
            serde_json::Value::Null => Some(path),
            serde_json::Value::Array(a) => a
                .iter()
                .enumerate()
                .find_map(|(i, x)| walk(x, format!("{path}[{i}]"))),
            serde_json::Value::Object(o) => o.iter().find_map(|(k, x)| {
                walk(
                    x,
                    if path.is_empty() {
                        k.clone()
                    } else {
                        format!("{path}.{k}")
                    },
                )
            }),
            _ => None,
        }
    }
    match v.as_object() {
        Some(o) => o
            .iter()
            .filter(|(k, _)| !optional.contains(&k.as_str()))
            .find_map(|(k, x)| walk(x, k.clone())),
        None => walk(v, String::new()),
    }
}

/// Seconds per step of `steps` steps that took `seconds`; 0 where none ran (a rerun of a
/// finished run), not that call's bookkeeping time as if it were one step's.
pub fn per_step(seconds: f64, steps: usize) -> f64 {
    if steps == 0 {
        0.0
    } else {
        seconds / steps as f64
    }
}

/// Memory the batches of a training may take together (estimated, bytes).
const MAX_BATCH_BYTES: f64 = 48.0 * (1u64 << 30) as f64;

/// Refuses `chains` trainings at once of `batch` frames of `w`×`h` native pixels each whose
/// batches would need more than 48 GiB: about 270 bytes per native pixel and frame in a
/// training step (its first step faulted in 4.4 GB for 16 frames of 1280×800,
/// docs/bench/chain.md). `what` names the setting in the message.
pub fn check_batch_memory(
    what: &str,
    batch: usize,
    chains: usize,
    w: usize,
    h: usize,
) -> Result<()> {
    let need = chains as f64 * batch as f64 * w as f64 * h as f64 * 270.0;
    if need > MAX_BATCH_BYTES {
        let gib = (1u64 << 30) as f64;
        bail!(
            "{what}: batch {batch} of {w}×{h} frames needs about {:.0} GiB through {chains} \
             chain(s), above the {:.0} GiB allowed; give a smaller batch or frame",
            need / gib,
            MAX_BATCH_BYTES / gib
        );
    }
    Ok(())
}

/// Environment variable that caps the memory a command plans for (bytes), below what the
/// system reports available: to leave room on a shared machine (and for the tests).
pub const MEMORY_ENV: &str = "NANOEYE_MEMORY_BYTES";

/// Memory (bytes) a command may plan to use: the smallest of [`MEMORY_ENV`], Linux's
/// `MemAvailable`, what the memory control groups allow and what the address-space limit
/// (`ulimit -v`) leaves this process; None where none of them is known.
pub fn memory_budget() -> Result<Option<u64>> {
    let cap = env_bytes(MEMORY_ENV, 1.0)?;
    let have = nanoeye_datagen::render::dataset::available_memory().map(|b| b as u64);
    Ok([cap, have, address_space_left()]
        .into_iter()
        .flatten()
        .min())
}

/// Resident bytes a plan may take under an address-space limit, as a share of the limit less
/// the resident set: the allocator reserves address space ahead of use, so the address space
/// of `sim` peaked at 2.0–2.6× its resident peak (`--aperture-step-um` 0.2 and 0.3: 5.15 GiB
/// for 2.54 GiB resident, 3.15 for 1.20; fifty-sixth session), and a plan estimated at 3.56
/// GiB under a 3.81 GiB `ulimit -v` passed the check and aborted on an allocation.
const ADDRESS_SPACE_SHARE: u64 = 2;

/// Bytes the soft `RLIMIT_AS` still leaves this process for a plan's resident memory, read
/// from /proc; None without a limit or where /proc cannot be read. Under `ulimit -v` an
/// allocation past it aborts the process, whatever memory the system has. The limit less the
/// resident set (`VmRSS`), not less `VmSize` (the allocator's first reservation of about 1 GiB
/// is address space it has not used and hands out again: that refused the default `optics
/// psf` under a limit it fits in), divided by [`ADDRESS_SPACE_SHARE`].
fn address_space_left() -> Option<u64> {
    let limits = std::fs::read_to_string("/proc/self/limits").ok()?;
    let soft: u64 = limits
        .lines()
        .find_map(|l| l.strip_prefix("Max address space"))?
        .split_whitespace()
        .next()?
        .parse()
        .ok()?;
    let used = nanoeye_datagen::render::dataset::proc_bytes("/proc/self/status", "VmRSS:")?;
    Some(soft.saturating_sub(used as u64) / ADDRESS_SPACE_SHARE)
}

/// Refuses a plan estimated at `need` bytes when it exceeds [`memory_budget`] (the kernel's
/// out-of-memory kill would end it instead of an error): `what` names the settings that set
/// the size, `fix` says which way to move them.
pub fn check_memory(what: &str, need: u64, fix: &str) -> Result<()> {
    if let Some(have) = memory_budget()?
        && need > have
    {
        let gib = (1u64 << 30) as f64;
        bail!(
            "{what}: needs about {:.2} GiB, more than the {:.2} GiB this process may use \
             (the least of {MEMORY_ENV}, MemAvailable, the cgroup limit and half what ulimit -v leaves); {fix}",
            need as f64 / gib,
            have as f64 / gib
        );
    }
    Ok(())
}

/// Environment variable that caps the disk space (bytes) a command counts as free where it
/// writes: to leave room on a shared disk (and for the tests).
pub const DISK_ENV: &str = "NANOEYE_DISK_BYTES";

/// Bytes an unprivileged writer may still write on the file system that holds `path` (or its
/// nearest existing ancestor), capped by [`DISK_ENV`]; None where neither is known.
pub fn disk_free(path: &Path) -> Result<Option<u64>> {
    let cap = env_bytes(DISK_ENV, 0.0)?;
    Ok([cap, fs_free(path)].into_iter().flatten().min())
}

/// The byte count environment variable `name` holds (a number ≥ `least`), None where unset.
fn env_bytes(name: &str, least: f64) -> Result<Option<u64>> {
    match std::env::var(name) {
        Ok(v) => Ok(Some(
            v.trim()
                .parse::<f64>()
                .ok()
                .filter(|b| b.is_finite() && *b >= least)
                .with_context(|| {
                    format!("{name}: expected a number of bytes ≥ {least}, got '{v}'")
                })? as u64,
        )),
        Err(_) => Ok(None),
    }
}

/// `statvfs`'s blocks available to unprivileged users × fragment size, for `path`'s nearest
/// existing ancestor.
#[cfg(unix)]
#[allow(clippy::unnecessary_cast)] // statvfs's field widths differ between targets
fn fs_free(path: &Path) -> Option<u64> {
    use std::os::unix::ffi::OsStrExt;
    let abs = std::path::absolute(path).ok()?;
    let dir = abs.ancestors().find(|a| a.exists())?;
    let c = std::ffi::CString::new(dir.as_os_str().as_bytes()).ok()?;
    // SAFETY: `c` is a NUL-terminated path and `st` a valid, writable statvfs for the call.
    let mut st: libc::statvfs = unsafe { std::mem::zeroed() };
    if unsafe { libc::statvfs(c.as_ptr(), &mut st) } != 0 {
        return None;
    }
    Some((st.f_bavail as u64).saturating_mul(st.f_frsize as u64))
}

#[cfg(not(unix))]
fn fs_free(_: &Path) -> Option<u64> {
    None
}

/// Bytes of the regular files under `dir` (0 where it does not exist); links are not followed.
pub fn bytes_under(dir: &Path) -> u64 {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return 0;
    };
    entries
        .flatten()
        .map(|e| match e.file_type() {
            Ok(t) if t.is_dir() => bytes_under(&e.path()),
            Ok(t) if t.is_file() => e.metadata().map_or(0, |m| m.len()),
            _ => 0,
        })
        .sum()
}

/// Refuses a job that will write at least `least` bytes under `out` when its disk has less
/// free (what `out` already holds counts as written: a resume reuses it), and warns when the
/// most it may write, `most`, does not fit: `what` names the job, `fix` what makes it smaller.
pub fn check_disk(what: &str, out: &Path, (least, most): (u64, u64), fix: &str) -> Result<()> {
    let Some(free) = disk_free(out)? else {
        return Ok(());
    };
    let there = bytes_under(out);
    let gb = |b: u64| b as f64 / 1e9;
    if least.saturating_sub(there) > free {
        bail!(
            "{what}: writes at least {:.2} GB under {} ({:.2} GB of it there already), but \
             {:.2} GB are free there; free space, choose another --out, or {fix}",
            gb(least),
            out.display(),
            gb(there),
            gb(free)
        );
    }
    if most.saturating_sub(there) > free {
        eprintln!(
            "warning: {what} may write up to {:.2} GB under {} ({:.2} GB of it there already), \
             more than the {:.2} GB free there; it stops with an error if the disk fills ({fix})",
            gb(most),
            out.display(),
            gb(there),
            gb(free)
        );
    }
    Ok(())
}

/// Largest small JSON input read (a subnet's arch, a rig, a state, a run's configuration): a
/// few hundred bytes in practice.
pub const MAX_ARCH_BYTES: u64 = 1 << 20;

/// Most values of a list flag whose every value multiplies the work (fisher's lenses and
/// pitches, gaze bias's solver radii).
pub const MAX_LIST: usize = 64;

/// The first value of `items` that an earlier one equals (a list flag given a value twice).
pub fn first_repeat<T: PartialEq>(items: &[T]) -> Option<&T> {
    items
        .iter()
        .enumerate()
        .find_map(|(i, x)| items[..i].contains(x).then_some(x))
}

/// The text of a small regular file at `path`, at most `max` bytes: a device or a FIFO
/// (`/dev/zero` read until memory ran out) or a file past `max` is refused before reading.
pub fn read_small_text(path: &Path, max: u64) -> Result<String> {
    let text = String::from_utf8(read_small(path, max)?)
        .with_context(|| format!("'{}' is not UTF-8 text", path.display()))?;
    // A byte-order mark some editors write first: JSON's RFC 8259 lets a reader ignore it,
    // and the JSONL readers did; an arch or a rig saved with one was refused.
    Ok(match text.strip_prefix('\u{feff}') {
        Some(rest) => rest.to_string(),
        None => text,
    })
}

/// Refuses an output directory that is, or lies inside, a rendered dataset (one holding
/// dataset.json): `search train --out DS` with DS its --dataset wrote a run into the data it
/// reads, exit 0.
pub fn check_not_dataset(out: &Path) -> Result<()> {
    // Resolved first: `new/../DS` names DS once `new` is made, but not while it is missing.
    let dir = resolved(out).unwrap_or_else(|| out.to_path_buf());
    if dir.join("dataset.json").symlink_metadata().is_ok() {
        bail!(
            "--out: '{}' is a dataset directory (it holds dataset.json); give another path",
            out.display()
        );
    }
    // Nor a directory inside one (`--out DS/frames` wrote a 100 MB checkpoint into a dataset).
    if let Some(ds) = dir
        .ancestors()
        .skip(1)
        .find(|d| d.join("dataset.json").symlink_metadata().is_ok())
    {
        bail!(
            "--out: '{}' lies inside the dataset directory '{}' (it holds dataset.json); give a \
             path outside it",
            out.display(),
            ds.display()
        );
    }
    Ok(())
}

/// Whether `path` is `dir` or lies below it, both [`resolved`] (an output inside an input's
/// tree).
pub fn is_inside(path: &Path, dir: &Path) -> bool {
    matches!((resolved(path), resolved(dir)), (Some(p), Some(d)) if p.starts_with(&d))
}

/// Whether two paths name one file (an output that would replace an input), each
/// [`resolved`]: `new/../rig.json` is rig.json once the command has made `new`.
pub fn same_file(a: &Path, b: &Path) -> bool {
    matches!((resolved(a), resolved(b)), (Some(x), Some(y)) if x == y)
}

/// `path` absolute with its links resolved, where it need not exist yet: its longest existing
/// ancestor canonicalized, the rest appended with `.` and `..` taken by name. That is where
/// the command's writes land: the directories it creates on the way are not links, so `..`
/// from one is its parent (`new/../rig.json` was not recognised as rig.json, and replaced it).
pub fn resolved(path: &Path) -> Option<PathBuf> {
    use std::path::Component;
    if let Ok(p) = path.canonicalize() {
        return Some(p);
    }
    let abs = if path.is_absolute() {
        path.to_path_buf()
    } else {
        std::env::current_dir().ok()?.join(path)
    };
    let parts: Vec<Component> = abs.components().collect();
    for k in (1..parts.len()).rev() {
        let Ok(mut base) = parts[..k].iter().collect::<PathBuf>().canonicalize() else {
            continue;
        };
        for c in &parts[k..] {
            match c {
                Component::CurDir => {}
                Component::ParentDir => {
                    base.pop();
                }
                Component::Normal(n) => base.push(n),
                Component::RootDir | Component::Prefix(_) => return None,
            }
        }
        return Some(base);
    }
    None
}

/// Largest record a command reads back from its own output directory (bytes): a run's
/// configuration or result, a resume's inputs, a few hundred KB at most.
pub const MAX_RECORD_BYTES: u64 = 64 << 20;

/// [`read_small_text`] of a record that may not exist yet: None where nothing is at `path`;
/// an error where something is there but is not a regular file of at most `max` bytes (a FIFO
/// blocked a resume, `/dev/zero` was read until memory ran out, and a directory was taken for
/// no record, skipping the comparison it holds).
pub fn read_record(path: &Path, max: u64) -> Result<Option<String>> {
    match path.symlink_metadata() {
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => Ok(None),
        _ => read_small_text(path, max).map(Some),
    }
}

/// [`read_small_text`]'s bytes, not required to be text.
pub fn read_small(path: &Path, max: u64) -> Result<Vec<u8>> {
    let meta =
        std::fs::metadata(path).with_context(|| format!("cannot read '{}'", path.display()))?;
    if !meta.is_file() {
        bail!("'{}' is not a regular file", path.display());
    }
    if meta.len() > max {
        bail!(
            "'{}' is {} bytes, more than the {max} expected",
            path.display(),
            meta.len()
        );
    }
    std::fs::read(path).with_context(|| format!("cannot read '{}'", path.display()))
}

/// Prints a serializable value as one line of JSON on stdout.
pub fn print_json<T: serde::Serialize>(value: &T) -> Result<()> {
    println!("{}", serde_json::to_string(value)?);
    Ok(())
}

/// Most values [`parse_range`] gives: its ranges are depth planes, each a PSF (and, in
/// `fisher`, its derivative) computed and held in memory.
pub const MAX_RANGE_VALUES: usize = 10_000;

/// Parses `a:b:step` (inclusive of `b` when it lies on the grid) or a single value `a`, at most
/// [`MAX_RANGE_VALUES`] values. `flag` names the parameter in the error message.
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
            // Count in f64: a tiny step or a span beyond f64 (-1e308:1e308) makes the quotient
            // +inf, and a saturating cast plus one overflowed (a panic in debug builds, an empty
            // range in release builds).
            let steps = ((b - a) / step + 1e-9).floor();
            if steps.is_nan() || steps >= MAX_RANGE_VALUES as f64 {
                bail!(
                    "{flag}: {:e} values (step {step:e}) is more than {MAX_RANGE_VALUES}",
                    steps + 1.0
                );
            }
            let n = steps as usize + 1;
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

    /// A path spelled as a directory is no output file, whether or not it exists (the write
    /// failed only after the work).
    #[test]
    fn a_path_spelled_as_a_directory_is_no_output_target() {
        let d = tempfile::tempdir().unwrap();
        let f = d.path().join("f");
        std::fs::write(&f, b"x").unwrap();
        for bad in ["q/", ".", "a/..", "a/.", "..", "/"] {
            let e = check_output_target(Path::new(bad)).unwrap_err().to_string();
            assert!(e.contains("names a directory"), "{bad}: {e}");
        }
        assert!(check_output_target(&d.path().join("f/")).is_err());
        check_output_target(&f).unwrap();
        check_output_target(&d.path().join("new.svg")).unwrap();
        check_output_target(Path::new("a/.b")).unwrap();
    }

    /// Seconds per step: the mean over the steps run, 0 where a call ran none (a finished
    /// run's rerun printed its bookkeeping time as one step's).
    #[test]
    fn seconds_per_step_is_zero_without_steps() {
        assert_eq!(per_step(6.0, 3), 2.0);
        assert_eq!(per_step(0.25, 0), 0.0);
    }

    /// A record of inputs that is no JSON object is refused, not taken as recording nothing
    /// (an array resumed a `fisher init` on another window size); an object is compared.
    #[test]
    fn a_record_of_inputs_that_is_no_object_is_refused() {
        let d = tempfile::tempdir().unwrap();
        let f = d.path().join("inputs.json");
        let now = serde_json::json!({"window_px": 30});
        let keys = [("window_px", "--window-px")];
        for bad in ["[9, 10.0]", "null", "7", "\"x\""] {
            std::fs::write(&f, bad).unwrap();
            let e = check_inputs(&f, &now, &keys, "--out").unwrap_err();
            assert!(
                format!("{e:#}").contains("not a JSON object"),
                "{bad}: {e:#}"
            );
        }
        std::fs::write(&f, r#"{"window_px": 9}"#).unwrap();
        let e = check_inputs(&f, &now, &keys, "--out").unwrap_err();
        assert!(e.to_string().starts_with("--window-px: differs"), "{e}");
        std::fs::write(&f, r#"{"window_px": 30}"#).unwrap();
        check_inputs(&f, &now, &keys, "--out").unwrap();
    }

    /// A path through directories not made yet resolves where the write lands; an existing
    /// link is followed, as the kernel does.
    #[test]
    fn resolved_takes_missing_directories_and_dots_by_name() {
        let d = tempfile::tempdir().unwrap();
        let root = d.path().canonicalize().unwrap();
        std::fs::write(root.join("f"), b"x").unwrap();
        let f = root.join("f");
        assert_eq!(resolved(&root.join("new/../f")), Some(f.clone()));
        assert_eq!(resolved(&root.join("a/./b/../../f")), Some(f.clone()));
        assert_eq!(resolved(&root.join("new/g")), Some(root.join("new/g")));
        assert!(same_file(&root.join("new/../f"), &f));
        assert!(!same_file(&root.join("new/f"), &f));
        #[cfg(unix)]
        {
            std::fs::create_dir_all(root.join("x/y")).unwrap();
            std::os::unix::fs::symlink(root.join("x/y"), root.join("l")).unwrap();
            // `l/..` is x (the link's target's parent), not the root.
            assert_eq!(
                resolved(&root.join("l/../new/g")),
                Some(root.join("x/new/g"))
            );
            assert_eq!(
                resolved(&root.join("l/new/../../f")),
                Some(root.join("x/f"))
            );
        }
    }

    #[test]
    fn batch_memory_is_estimated_from_the_measured_step() {
        // The measured case: 16 frames of 1280×800, 4.4 GB (one chain); three at once too.
        assert!(check_batch_memory("--batch", 16, 1, 1280, 800).is_ok());
        assert!(check_batch_memory("--batch", 16, 3, 1280, 800).is_ok());
        let e = check_batch_memory("--batch", 4096, 1, 1280, 800).unwrap_err();
        assert!(e.to_string().starts_with("--batch: batch 4096") && e.to_string().contains("GiB"));
    }

    #[test]
    fn first_null_names_the_path_of_a_non_finite_number() {
        let v = serde_json::json!({"a": 1.0, "rig": null, "b": {"c": [0.5, f64::NAN]}});
        assert_eq!(first_null(&v, &["rig"]).as_deref(), Some("b.c[1]"));
        let v = serde_json::json!({"a": 1.0, "rig": null});
        assert_eq!(first_null(&v, &[]).as_deref(), Some("rig"));
        assert_eq!(first_null(&v, &["rig"]), None);
        let v = serde_json::json!({"a": [1, {"x": f64::INFINITY}]});
        assert_eq!(first_null(&v, &[]).as_deref(), Some("a[1].x"));
        assert_eq!(first_null(&serde_json::json!({"a": [1.0]}), &[]), None);
    }

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
    fn range_counts_beyond_the_limit_or_beyond_f64_are_refused() {
        // The quotient is +inf: it overflowed usize (a panic in debug builds).
        for text in ["0:1e300:1e-300", "-1e308:1e308:1", "20:22:1e-6"] {
            let e = parse_range("--depths-mm", text).unwrap_err().to_string();
            assert!(
                e.starts_with("--depths-mm:") && e.contains("more than"),
                "{e}"
            );
        }
        let last = format!("0:{}:1", MAX_RANGE_VALUES - 1);
        assert_eq!(parse_range("--x", &last).unwrap().len(), MAX_RANGE_VALUES);
        let over = format!("0:{}:1", MAX_RANGE_VALUES);
        assert!(parse_range("--x", &over).is_err());
    }

    #[test]
    fn jsonl_line_strips_bom_and_endings_and_rejects_bad_utf8() {
        assert_eq!(jsonl_line(b"\xEF\xBB\xBF{}\r\n", 1).unwrap(), "{}");
        assert_eq!(jsonl_line(b"{}\n", 2).unwrap(), "{}");
        let e = jsonl_line(b"{\xFF}\n", 3).unwrap_err().to_string();
        assert!(e.contains("UTF-8"), "{e}");
    }

    #[cfg(unix)]
    #[test]
    fn atomic_write_refuses_symlinks_and_removes_dead_temps() {
        let dir = tempfile::tempdir().unwrap();
        let real = dir.path().join("real.txt");
        std::fs::write(&real, b"keep").unwrap();
        let link = dir.path().join("link.txt");
        std::os::unix::fs::symlink(&real, &link).unwrap();
        let e = write_atomic(&link, b"x").unwrap_err().to_string();
        assert!(e.contains("symbolic link"), "{e}");
        assert!(
            std::fs::symlink_metadata(&link)
                .unwrap()
                .file_type()
                .is_symlink()
        );
        assert_eq!(std::fs::read(&real).unwrap(), b"keep");
        // A temp file of a process that no longer exists (pid beyond any real one).
        let dead = dir.path().join(format!("{TMP_PREFIX}4294967295-abc"));
        std::fs::write(&dead, b"partial").unwrap();
        write_atomic(&dir.path().join("out.txt"), b"ok").unwrap();
        assert!(!dead.exists());
        // An output's mode is what `File::create` gives under this umask, not 0600.
        use std::os::unix::fs::PermissionsExt;
        let plain = dir.path().join("plain.txt");
        std::fs::write(&plain, b"ok").unwrap();
        let mode = |p: &Path| std::fs::metadata(p).unwrap().permissions().mode() & 0o777;
        assert_eq!(mode(&dir.path().join("out.txt")), mode(&plain));
    }

    #[cfg(unix)]
    #[test]
    fn dead_temps_are_removed_in_every_directory_below_and_live_ones_kept() {
        let dir = tempfile::tempdir().unwrap();
        let deep = dir.path().join("a/b");
        std::fs::create_dir_all(&deep).unwrap();
        let dead = [
            dir.path().join(format!("{TMP_PREFIX}4294967295-x")),
            deep.join(format!("{TMP_PREFIX}4294967295-y")),
        ];
        let live = deep.join(format!("{TMP_PREFIX}{}-z", std::process::id()));
        let data = deep.join("checkpoint.bin");
        for f in dead.iter().chain([&live, &data]) {
            std::fs::write(f, b"x").unwrap();
        }
        // A link to another tree is not followed.
        let other = tempfile::tempdir().unwrap();
        let outside = other.path().join(format!("{TMP_PREFIX}4294967295-w"));
        std::fs::write(&outside, b"x").unwrap();
        std::os::unix::fs::symlink(other.path(), dir.path().join("link")).unwrap();
        remove_stale_temps_under(dir.path());
        assert!(dead.iter().all(|f| !f.exists()));
        assert!(live.exists() && data.exists() && outside.exists());
    }

    #[test]
    fn digest_is_fnv1a_and_a_file_digests_as_its_bytes() {
        // FNV-1a 64 of "" and of "a" (the published test vectors).
        assert_eq!(Digest::default().hex(), "cbf29ce484222325");
        let mut d = Digest::default();
        d.bytes(b"a");
        assert_eq!(d.hex(), "af63dc4c8601ec8c");
        let dir = tempfile::tempdir().unwrap();
        let p = dir.path().join("f");
        let data: Vec<u8> = (0..3_000_000u32).map(|i| (i * 7 % 251) as u8).collect();
        std::fs::write(&p, &data).unwrap();
        let (mut a, mut b) = (Digest::default(), Digest::default());
        assert_eq!(a.file(&p).unwrap(), data.len() as u64);
        b.bytes(&data);
        assert_eq!(a.hex(), b.hex());
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
