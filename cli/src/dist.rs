//! Ranks of a distributed run: every byte that crosses MPI goes through this module.
//!
//! Built with the cargo feature `mpi`, `nanoeye` started under `mpirun -np N` runs as N ranks
//! over MPI_COMM_WORLD; without the feature (or started alone) it is rank 0 of 1 and every
//! operation below is the identity. Commands are written once against [`World`], so a
//! single-process run and an N-rank run execute the same code on the same items. Messages are
//! plain bytes; what they hold is the business of the command that sends them.
//! The library crates know nothing of MPI: they take lists of items (pitches, frames, depths,
//! candidates) and return their results.

use std::sync::OnceLock;

/// Rank and size of this process in the run.
#[derive(Debug, Clone, Copy)]
pub struct World {
    rank: usize,
    size: usize,
}

static WORLD: OnceLock<World> = OnceLock::new();

/// Keeps MPI initialised for the life of `main` (finalises it on drop).
pub struct Session {
    #[cfg(feature = "mpi")]
    _universe: Option<mpi::environment::Universe>,
}

/// Initialises MPI (with the feature) and records this process's rank; call once, first thing
/// in `main`, and keep the returned session alive until the end.
pub fn init() -> Session {
    #[cfg(feature = "mpi")]
    {
        use mpi::traits::Communicator;
        // Started without a launcher, the binary stays a plain process: an MPI singleton
        // would only add start-up time (and OpenMPI's refusal to run as root).
        let launched = ["OMPI_COMM_WORLD_SIZE", "PMI_SIZE", "PMIX_RANK"]
            .iter()
            .any(|v| std::env::var_os(v).is_some());
        // Only the main thread calls MPI; rayon workers never do.
        let universe = if launched {
            mpi::initialize_with_threading(mpi::Threading::Funneled).map(|(universe, _)| universe)
        } else {
            None
        };
        let w = match &universe {
            Some(u) => {
                let c = u.world();
                World {
                    rank: c.rank() as usize,
                    size: c.size() as usize,
                }
            }
            None => World { rank: 0, size: 1 },
        };
        let _ = WORLD.set(w);
        Session {
            _universe: universe,
        }
    }
    #[cfg(not(feature = "mpi"))]
    {
        let _ = WORLD.set(World { rank: 0, size: 1 });
        Session {}
    }
}

/// This process's place in the run (rank 0 of 1 before [`init`] or without MPI).
pub fn world() -> World {
    WORLD.get().copied().unwrap_or(World { rank: 0, size: 1 })
}

/// Items `0..n` this rank owns under a round-robin split (item i goes to rank i mod size):
/// frames and depths cost about the same each, so this balances them.
pub fn round_robin(n: usize, w: World) -> Vec<usize> {
    (w.rank..n).step_by(w.size).collect()
}

#[cfg(feature = "mpi")]
fn comm() -> mpi::topology::SimpleCommunicator {
    mpi::topology::SimpleCommunicator::world()
}

/// Message tags of the search's worker pool.
pub const TAG_TASK: i32 = 1;
/// Tag of a worker's reply.
pub const TAG_RESULT: i32 = 2;
/// Tag that tells a worker to stop.
pub const TAG_STOP: i32 = 3;

impl World {
    /// This rank (0-based).
    pub fn rank(&self) -> usize {
        self.rank
    }
    /// Number of ranks.
    pub fn size(&self) -> usize {
        self.size
    }
    /// Whether this is rank 0, the one that writes shared outputs and prints results.
    pub fn is_root(&self) -> bool {
        self.rank == 0
    }
    /// Whether more than one rank takes part.
    pub fn is_distributed(&self) -> bool {
        self.size > 1
    }

    /// Ends every rank of the run at once after this rank printed why (MPI_Abort); finished
    /// shares already on disk stay there for the resume.
    pub fn abort(&self, code: i32) -> ! {
        #[cfg(feature = "mpi")]
        if self.size > 1 {
            use mpi::traits::Communicator;
            comm().abort(code);
        }
        std::process::exit(code)
    }

    /// Waits until every rank gets here.
    pub fn barrier(&self) {
        #[cfg(feature = "mpi")]
        if self.size > 1 {
            use mpi::traits::CommunicatorCollectives;
            comm().barrier();
        }
    }

    /// Rank 0's `bytes` on every rank (other ranks' arguments are ignored).
    pub fn broadcast(&self, bytes: Vec<u8>) -> Vec<u8> {
        #[cfg(feature = "mpi")]
        if self.size > 1 {
            use mpi::traits::{Communicator, Root};
            let c = comm();
            let root = c.process_at_rank(0);
            let mut len = bytes.len() as u64;
            root.broadcast_into(&mut len);
            let mut buf = if self.is_root() {
                bytes
            } else {
                vec![0u8; len as usize]
            };
            for chunk in buf.chunks_mut(CHUNK) {
                root.broadcast_into(chunk);
            }
            return buf;
        }
        bytes
    }

    /// On rank 0, every rank's `bytes` in rank order; `None` on the other ranks.
    pub fn gather(&self, bytes: Vec<u8>) -> Option<Vec<Vec<u8>>> {
        #[cfg(feature = "mpi")]
        if self.size > 1 {
            let c = comm();
            if self.is_root() {
                let mut all = vec![bytes];
                for r in 1..self.size {
                    all.push(recv_from(&c, r as i32, TAG_GATHER));
                }
                return Some(all);
            }
            send_to(&c, 0, TAG_GATHER, &bytes);
            return None;
        }
        Some(vec![bytes])
    }

    /// Every rank's `bytes`, in rank order, on every rank (the AllGather of a PSF stack).
    pub fn all_gather(&self, bytes: Vec<u8>) -> Vec<Vec<u8>> {
        if self.size == 1 {
            return vec![bytes];
        }
        let framed = self
            .gather(bytes)
            .map(|all| frame(&all))
            .unwrap_or_default();
        unframe(&self.broadcast(framed))
    }

    /// Sends `bytes` to rank `to` with `tag` (the search's worker pool).
    pub fn send(&self, to: usize, tag: i32, bytes: &[u8]) {
        #[cfg(feature = "mpi")]
        if self.size > 1 {
            send_to(&comm(), to as i32, tag, bytes);
            return;
        }
        let _ = (to, tag, bytes);
        unreachable_single("send");
    }

    /// Receives the next message from any rank: (source rank, tag, bytes).
    pub fn receive_any(&self) -> (usize, i32, Vec<u8>) {
        #[cfg(feature = "mpi")]
        if self.size > 1 {
            use mpi::traits::{Communicator, Source};
            let c = comm();
            let (msg, status) = c.any_process().matched_probe();
            let tag = status.tag();
            let src = status.source_rank();
            let (len, _) = msg.matched_receive::<u64>();
            let bytes = recv_body(&c, src, tag, len as usize);
            return (src as usize, tag, bytes);
        }
        unreachable_single("receive_any")
    }
}

/// The ranks sharing the depth planes of a camera chain's PSF stacks and PSF VJPs
/// (`search train`): each computes its share of the depths, and [`World::all_gather`] gives
/// every rank every plane (f64, exact). Every rank must run the same training.
pub struct RankSplit {
    w: World,
    /// Nanoseconds spent in the all-gathers (waiting for the slowest rank included).
    gather_ns: std::sync::atomic::AtomicU64,
    gathers: std::sync::atomic::AtomicU64,
}

impl RankSplit {
    /// The split over the ranks of `w`.
    pub fn new(w: World) -> RankSplit {
        RankSplit {
            w,
            gather_ns: Default::default(),
            gathers: Default::default(),
        }
    }

    /// (all-gathers so far, seconds spent in them on this rank, the wait for the slowest
    /// rank's share included).
    pub fn gather_time(&self) -> (u64, f64) {
        use std::sync::atomic::Ordering::Relaxed;
        (
            self.gathers.load(Relaxed),
            self.gather_ns.load(Relaxed) as f64 * 1e-9,
        )
    }
}

impl nanoeye_search::DepthSplit for RankSplit {
    fn parts(&self) -> usize {
        self.w.size
    }
    fn part(&self) -> usize {
        self.w.rank
    }
    fn all_gather(&self, values: Vec<f64>) -> nanoeye_search::Result<Vec<Vec<f64>>> {
        use std::sync::atomic::Ordering::Relaxed;
        let t = std::time::Instant::now();
        let all = self
            .w
            .all_gather(f64_bytes(&values))
            .iter()
            .map(|b| bytes_f64(b))
            .collect();
        self.gather_ns
            .fetch_add(t.elapsed().as_nanos() as u64, Relaxed);
        self.gathers.fetch_add(1, Relaxed);
        Ok(all)
    }
}

/// A gather's messages carry this tag, so they never match a worker-pool message.
#[cfg(feature = "mpi")]
const TAG_GATHER: i32 = 100;

/// Largest piece one MPI call moves: counts are C ints, and a full sweep is ~66 MB.
#[cfg(feature = "mpi")]
const CHUNK: usize = 1 << 28;

/// Sends a length header, then the body in chunks (all with `tag`).
#[cfg(feature = "mpi")]
fn send_to(c: &mpi::topology::SimpleCommunicator, to: i32, tag: i32, bytes: &[u8]) {
    use mpi::traits::{Communicator, Destination};
    let p = c.process_at_rank(to);
    p.send_with_tag(&(bytes.len() as u64), tag);
    for chunk in bytes.chunks(CHUNK) {
        p.send_with_tag(chunk, tag);
    }
}

#[cfg(feature = "mpi")]
fn recv_from(c: &mpi::topology::SimpleCommunicator, from: i32, tag: i32) -> Vec<u8> {
    use mpi::traits::{Communicator, Source};
    let (len, _) = c.process_at_rank(from).receive_with_tag::<u64>(tag);
    recv_body(c, from, tag, len as usize)
}

#[cfg(feature = "mpi")]
fn recv_body(c: &mpi::topology::SimpleCommunicator, from: i32, tag: i32, len: usize) -> Vec<u8> {
    use mpi::traits::{Communicator, Source};
    let mut out = Vec::with_capacity(len);
    while out.len() < len {
        let (chunk, _) = c.process_at_rank(from).receive_vec_with_tag::<u8>(tag);
        out.extend_from_slice(&chunk);
    }
    out
}

fn unreachable_single(what: &str) -> ! {
    // A single process has no peer; the worker pool is only built with more than one rank.
    eprintln!("internal error: {what} called in a single-process run");
    std::process::exit(2)
}

/// Length-prefixed concatenation of byte strings.
pub fn frame(parts: &[Vec<u8>]) -> Vec<u8> {
    let mut out = Vec::new();
    out.extend_from_slice(&(parts.len() as u64).to_le_bytes());
    for p in parts {
        out.extend_from_slice(&(p.len() as u64).to_le_bytes());
        out.extend_from_slice(p);
    }
    out
}

/// Inverse of [`frame`] (an empty or short input gives what it holds).
pub fn unframe(bytes: &[u8]) -> Vec<Vec<u8>> {
    let mut out = Vec::new();
    let mut at = 0usize;
    let next_u64 = |at: &mut usize| -> Option<u64> {
        let b = bytes.get(*at..*at + 8)?;
        *at += 8;
        Some(u64::from_le_bytes(b.try_into().ok()?))
    };
    let Some(n) = next_u64(&mut at) else {
        return out;
    };
    for _ in 0..n {
        let Some(len) = next_u64(&mut at) else { break };
        let Some(p) = bytes.get(at..at + len as usize) else {
            break;
        };
        out.push(p.to_vec());
        at += len as usize;
    }
    out
}

/// f64 values as little-endian bytes.
pub fn f64_bytes(v: &[f64]) -> Vec<u8> {
    v.iter().flat_map(|x| x.to_le_bytes()).collect()
}

/// Inverse of [`f64_bytes`] (trailing bytes short of 8 are ignored).
pub fn bytes_f64(b: &[u8]) -> Vec<f64> {
    b.chunks_exact(8)
        .map(|c| f64::from_le_bytes(c.try_into().unwrap_or([0; 8])))
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frames_round_trip_including_empty_parts() {
        let parts = vec![vec![], vec![1u8, 2, 3], vec![255; 17]];
        assert_eq!(unframe(&frame(&parts)), parts);
        assert!(unframe(&[]).is_empty());
        let v = [0.0, -1.5, f64::MAX, f64::NAN];
        let back = bytes_f64(&f64_bytes(&v));
        assert_eq!(
            back.iter().map(|x| x.to_bits()).collect::<Vec<_>>(),
            v.iter().map(|x| x.to_bits()).collect::<Vec<_>>()
        );
    }

    #[test]
    fn round_robin_shares_cover_every_item_once() {
        for size in 1..5 {
            let mut all: Vec<usize> = (0..size)
                .flat_map(|rank| round_robin(11, World { rank, size }))
                .collect();
            all.sort_unstable();
            assert_eq!(all, (0..11).collect::<Vec<_>>());
        }
    }
}
