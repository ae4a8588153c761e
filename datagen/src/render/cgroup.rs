//! The memory a Linux control group still lets this process use: a container's limit
//! (`docker run --memory`, a batch system's job) is not in `/proc/meminfo`, whose
//! `MemAvailable` is the whole machine's, so a plan that fits the machine but not the group
//! ends in the kernel's out-of-memory kill instead of an error.

use std::path::{Path, PathBuf};

/// Bytes the memory control groups of this process still allow (the least, over the group and
/// its ancestors, of limit less usage, page cache that can be dropped not counted as usage);
/// None where no group sets a limit or none can be read. Reads cgroup v2 and v1.
pub fn memory_left() -> Option<usize> {
    let own = std::fs::read_to_string("/proc/self/cgroup").ok()?;
    memory_left_under(&own, Path::new("/sys/fs/cgroup"))
}

/// [`memory_left`] for the `/proc/self/cgroup` text `own`, with the hierarchies mounted under
/// `root` (`/sys/fs/cgroup`).
pub fn memory_left_under(own: &str, root: &Path) -> Option<usize> {
    let mut least: Option<u64> = None;
    for line in own.lines() {
        let mut parts = line.splitn(3, ':');
        let (Some(id), Some(controllers), Some(path)) = (parts.next(), parts.next(), parts.next())
        else {
            continue;
        };
        let found = if id == "0" && controllers.is_empty() {
            // v2: mounted at the root on a pure v2 system, at unified/ on a hybrid one.
            [root.to_path_buf(), root.join("unified")]
                .into_iter()
                .filter_map(|m| left_in(&m, path, V2))
                .min()
        } else if controllers.split(',').any(|c| c == "memory") {
            left_in(&root.join("memory"), path, V1)
        } else {
            None
        };
        least = match (least, found) {
            (Some(a), Some(b)) => Some(a.min(b)),
            (a, b) => a.or(b),
        };
    }
    least.map(|b| usize::try_from(b).unwrap_or(usize::MAX))
}

/// The file names of one cgroup version: limit, usage, and the `memory.stat` key of the page
/// cache the kernel drops before it kills.
struct Files {
    limit: &'static str,
    usage: &'static str,
    inactive_file: &'static str,
}

const V2: Files = Files {
    limit: "memory.max",
    usage: "memory.current",
    inactive_file: "inactive_file",
};

const V1: Files = Files {
    limit: "memory.limit_in_bytes",
    usage: "memory.usage_in_bytes",
    inactive_file: "total_inactive_file",
};

/// v1's "no limit" is a page-rounded `i64::MAX`; anything above 2⁶² bytes is no limit.
const NO_LIMIT: u64 = 1 << 62;

/// The least room over the group at `path` (in the hierarchy mounted at `mount`) and its
/// ancestors that set a limit. Inside a container the group's own path is often not under the
/// mount (the mount's root is the container's group): then the mount's root is read.
fn left_in(mount: &Path, path: &str, files: Files) -> Option<u64> {
    let rel = path.trim_start_matches('/');
    let mut dir: PathBuf = mount.join(rel);
    if rel.is_empty() || !dir.is_dir() {
        dir = mount.to_path_buf();
    }
    let mut least: Option<u64> = None;
    loop {
        if let Some(room) = room_in(&dir, &files) {
            least = Some(least.map_or(room, |l| l.min(room)));
        }
        if dir.as_path() == mount || !dir.pop() || !dir.starts_with(mount) {
            break;
        }
    }
    least
}

/// Limit less usage (less inactive page cache) of the one group in `dir`; None without a
/// limit or where its files cannot be read.
fn room_in(dir: &Path, files: &Files) -> Option<u64> {
    let read = |name: &str| std::fs::read_to_string(dir.join(name)).ok();
    let limit: u64 = read(files.limit)?.trim().parse().ok()?;
    if limit >= NO_LIMIT {
        return None;
    }
    let usage: u64 = read(files.usage)
        .and_then(|t| t.trim().parse().ok())
        .unwrap_or(0);
    let cache: u64 = read("memory.stat")
        .and_then(|t| {
            t.lines().find_map(|l| {
                let (k, v) = l.split_once(' ')?;
                (k == files.inactive_file).then(|| v.trim().parse().ok())?
            })
        })
        .unwrap_or(0);
    Some(limit.saturating_sub(usage.saturating_sub(cache)))
}

#[cfg(test)]
mod tests {
    use super::*;

    fn write(dir: &Path, name: &str, text: &str) {
        std::fs::create_dir_all(dir).unwrap();
        std::fs::write(dir.join(name), text).unwrap();
    }

    /// v2 (pure and hybrid) and v1, a limit on the group itself or on an ancestor, page cache
    /// not counted, "max" and v1's huge value read as no limit, and a container's view where
    /// the group's path is not under the mount.
    #[test]
    fn room_is_the_least_limit_less_usage_over_the_group_and_its_ancestors() {
        let t = tempfile::tempdir().unwrap();
        let root = t.path();
        let gib = 1u64 << 30;
        // Pure v2: the job's group has no limit, its parent 4 GiB with 3 GiB used of which
        // 1 GiB is inactive page cache: 2 GiB left.
        let job = root.join("batch/job7");
        write(&job, "memory.max", "max\n");
        write(&job, "memory.current", &format!("{}\n", gib));
        write(&root.join("batch"), "memory.max", &format!("{}\n", 4 * gib));
        write(
            &root.join("batch"),
            "memory.current",
            &format!("{}\n", 3 * gib),
        );
        let stat = format!("anon 123\ninactive_file {}\nactive_file 5\n", gib);
        write(&root.join("batch"), "memory.stat", &stat);
        let own = "0::/batch/job7\n";
        assert_eq!(memory_left_under(own, root), Some(2 * gib as usize));
        // A tighter limit on the group itself wins.
        write(&job, "memory.max", &format!("{}\n", gib + 4096));
        assert_eq!(memory_left_under(own, root), Some(4096));
        // Usage above the limit leaves none, not a wrapped count.
        write(&job, "memory.current", &format!("{}\n", 2 * gib));
        assert_eq!(memory_left_under(own, root), Some(0));

        // v1 beside a v2 hierarchy without limits (hybrid): the memory controller's group.
        let t1 = tempfile::tempdir().unwrap();
        let r1 = t1.path();
        let g = r1.join("memory/process_api/abc");
        write(&g, "memory.limit_in_bytes", "9223372036854771712\n");
        write(&g, "memory.usage_in_bytes", "736718848\n");
        write(&r1.join("unified"), "memory.max", "max\n");
        let own1 = "9:name=systemd:/\n4:memory:/process_api/abc\n0::/\n";
        assert_eq!(memory_left_under(own1, r1), None, "no limit anywhere");
        write(&g, "memory.limit_in_bytes", &format!("{}\n", 8 * gib));
        write(
            &g,
            "memory.stat",
            "cache 9\ntotal_inactive_file 104857600\n",
        );
        assert_eq!(
            memory_left_under(own1, r1),
            Some((8 * gib - (736718848 - 104857600)) as usize)
        );

        // A container: /proc/self/cgroup names the host's path, the mount's root is the
        // container's own group.
        let t2 = tempfile::tempdir().unwrap();
        let r2 = t2.path();
        write(r2, "memory.max", &format!("{}\n", 512 << 20));
        write(r2, "memory.current", &format!("{}\n", 100 << 20));
        let own2 = "0::/system.slice/docker-1234.scope\n";
        assert_eq!(memory_left_under(own2, r2), Some(412 << 20));

        // Nothing readable, or a malformed line: no limit known.
        assert_eq!(memory_left_under("garbage\n", r2), None);
        assert_eq!(memory_left_under("", r2), None);
    }
}
