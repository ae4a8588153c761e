//! Depth planes of a step's PSF stack and PSF VJP shared out among processes (the paper's
//! AllGather), behind a small trait so that this crate knows nothing of how processes talk.
//!
//! A [`CameraChain`](crate::CameraChain) computes every PSF stack and every PSF VJP through
//! its [`DepthSplit`]: the depths that need work are dealt out round-robin
//! ([`share`]), each process computes its own, and an all-gather gives every process every
//! depth's result. What is then done with them (the stack's normalisation, the sum of the VJP
//! terms in increasing depth) is the same code on every process and on a single one, so a split
//! run holds the same bits as [`OneProcess`]. The CLI implements the trait over MPI.

use crate::error::{Result, param};

/// Processes that share the depth planes of a chain's PSF work. Every method that moves data
/// is a collective: every process calls it, at the same point of the same computation.
pub trait DepthSplit: Send + Sync {
    /// Number of processes (≥ 1).
    fn parts(&self) -> usize;
    /// This process, `0..parts()`.
    fn part(&self) -> usize;
    /// Every process's `values`, in process order, on every process.
    fn all_gather(&self, values: Vec<f64>) -> Result<Vec<Vec<f64>>>;
}

/// A single process: it computes every depth, and the gather is the identity.
#[derive(Clone, Copy, Debug, Default)]
pub struct OneProcess;

impl DepthSplit for OneProcess {
    fn parts(&self) -> usize {
        1
    }
    fn part(&self) -> usize {
        0
    }
    fn all_gather(&self, values: Vec<f64>) -> Result<Vec<Vec<f64>>> {
        Ok(vec![values])
    }
}

/// The items of `items` that process `part` of `parts` computes: positions part, part + parts,
/// … (depths of one stack cost about the same each, so this balances them).
pub fn share(items: &[usize], parts: usize, part: usize) -> Vec<usize> {
    items
        .iter()
        .skip(part)
        .step_by(parts.max(1))
        .copied()
        .collect()
}

/// Runs `compute` on this process's [`share`] of `items` (it returns one vector of `len`
/// values per item it is given, in that order) and returns every item's vector, in the order of
/// `items`, on every process.
pub fn map_gather(
    split: &dyn DepthSplit,
    items: &[usize],
    len: usize,
    compute: impl FnOnce(&[usize]) -> Result<Vec<Vec<f64>>>,
) -> Result<Vec<Vec<f64>>> {
    let (parts, part) = (split.parts(), split.part());
    if parts == 0 || part >= parts {
        return Err(param(
            "split",
            format!("process {part} of {parts} does not exist"),
        ));
    }
    let mine = share(items, parts, part);
    let local = compute(&mine)?;
    if local.len() != mine.len() || local.iter().any(|v| v.len() != len) {
        return Err(param(
            "split",
            format!(
                "computed {} results for {} items (each must hold {len} values)",
                local.len(),
                mine.len()
            ),
        ));
    }
    if parts == 1 {
        return Ok(local);
    }
    let all = split.all_gather(local.concat())?;
    if all.len() != parts {
        return Err(param(
            "split",
            format!(
                "the gather returned {} shares for {parts} processes",
                all.len()
            ),
        ));
    }
    let mut out: Vec<Vec<f64>> = vec![Vec::new(); items.len()];
    for (p, values) in all.iter().enumerate() {
        let n = share(items, parts, p).len();
        if values.len() != n * len {
            return Err(param(
                "split",
                format!(
                    "process {p} sent {} values for its {n} items of {len}",
                    values.len()
                ),
            ));
        }
        // (len = 0: nothing to copy, every item's vector stays empty.)
        for (i, v) in values.chunks_exact(len.max(1)).enumerate() {
            out[p + i * parts] = v.to_vec();
        }
    }
    Ok(out)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn shares_cover_every_item_once_in_position_order() {
        let items = [3, 4, 7, 9, 10];
        assert_eq!(share(&items, 1, 0), items);
        assert_eq!(share(&items, 2, 0), [3, 7, 10]);
        assert_eq!(share(&items, 2, 1), [4, 9]);
        assert_eq!(share(&items, 6, 5), Vec::<usize>::new());
    }

    #[test]
    fn one_process_computes_everything_once() {
        let got = map_gather(&OneProcess, &[2, 5], 2, |mine| {
            assert_eq!(mine, [2, 5]);
            Ok(mine.iter().map(|&k| vec![k as f64, -(k as f64)]).collect())
        })
        .unwrap();
        assert_eq!(got, vec![vec![2.0, -2.0], vec![5.0, -5.0]]);
        let bad = map_gather(&OneProcess, &[2, 5], 2, |_| Ok(vec![vec![0.0; 2]]));
        assert!(bad.is_err());
    }
}
