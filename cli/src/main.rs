//! `nanoeye`: the command-line interface of the nanoeye workspace.
//!
//! One subcommand group per stage crate; every command that prints results takes `--json`.
//! Errors name the offending parameter and exit non-zero; outputs are written atomically.

mod compare;
mod datagen;
mod datagen_render;
mod dist;
mod embed;
mod figures;
mod fisher;
mod gaze;
mod metalib;
mod nets;
mod optics;
mod pareto;
mod report;
mod rig;
mod run;
mod safety;
mod sensor;
mod sim;
mod track;
mod train;
mod util;

use clap::{Parser, Subcommand};
use std::io::IsTerminal;
use std::process::ExitCode;

/// nanoeye: co-designed nano-optical eye tracking, every stage from pillars to gaze.
#[derive(Parser)]
#[command(name = "nanoeye", version, about, propagate_version = true)]
struct Cli {
    #[command(subcommand)]
    command: Command,
}

#[derive(Subcommand)]
enum Command {
    /// The main job: render → co-design training → REA → protocol gaze error, with a report.
    Run(run::RunArgs),
    /// Eye–camera rig.
    #[command(subcommand)]
    Rig(rig::Cmd),
    /// Geometric gaze solver (S9–S14).
    #[command(subcommand)]
    Gaze(gaze::Cmd),
    /// State sampling and rendering (C.1–C.4, D.4).
    #[command(subcommand)]
    Datagen(datagen::Cmd),
    // Each stage adds its group here (one variant) and its arm in `dispatch`.
    /// Networks: supernet cost model (S23) and toy training.
    #[command(subcommand)]
    Nets(nets::NetsCmd),
    /// Nanopillar library: RCWA cell, sweep, selection, blueprint.
    #[command(subcommand)]
    Metalib(metalib::MetalibCmd),
    /// Metasurface optics: PSF stacks over depth.
    #[command(subcommand)]
    Optics(optics::Cmd),
    /// Sensor model: pitch integration, noise, ADC (S2, S24).
    #[command(subcommand)]
    Sensor(sensor::Cmd),
    /// Fisher-information design losses, initialization loop, PSF analysis (S3–S6, S25, A.2, E).
    #[command(subcommand)]
    Fisher(fisher::Cmd),
    /// A rendered dataset through the simulated camera: lens → S1 → sensor at p̂ (S1, S2).
    Sim(sim::SimArgs),
    /// Co-design: task loss and gradients through the camera chain (S7, S8, S16–S22).
    #[command(subcommand)]
    Search(sim::SearchCmd),
    /// Sensor frames → gaze, one JSON line per frame, with a trained run (A.4).
    Track(track::TrackArgs),
    /// Largest eye-safe LED intensity for glint illumination, indoors and outdoors (D.5).
    Safety(safety::SafetyArgs),
    /// Finished `run` jobs side by side: per lens and per setting, paired over seeds.
    Compare(compare::CompareArgs),
}

fn dispatch(command: Command) -> anyhow::Result<()> {
    match command {
        Command::Run(a) => run::run(a),
        Command::Rig(c) => rig::run(c),
        Command::Gaze(c) => gaze::run(c),
        Command::Datagen(c) => datagen::run(c),
        Command::Metalib(c) => metalib::run(c),
        Command::Optics(c) => optics::run(c),
        Command::Sensor(c) => sensor::run(c),
        Command::Fisher(c) => fisher::run(c),
        Command::Nets(c) => nets::run(c),
        Command::Sim(a) => sim::sim(a),
        Command::Search(c) => sim::search(c),
        Command::Track(a) => track::track(a),
        Command::Safety(a) => safety::run(a),
        Command::Compare(a) => compare::run(a),
    }
}

/// Whether `command` splits its work across MPI ranks; the others refuse to run on more
/// than one, since every rank would write the same outputs.
fn distributes(command: &Command) -> bool {
    matches!(
        command,
        Command::Metalib(metalib::MetalibCmd::Sweep(_))
            | Command::Datagen(datagen::Cmd::Render(_))
            | Command::Optics(optics::Cmd::Psf(_))
            | Command::Search(sim::SearchCmd::Rea(_))
            | Command::Search(sim::SearchCmd::Train(_))
    )
}

/// AVX2 and FMA in the CPU and enabled by the OS, asked of CPUID itself:
/// `is_x86_feature_detected!` answers true without asking when the build enables the feature.
#[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
fn cpu_has_avx2_fma() -> bool {
    use std::arch::x86_64::{__cpuid, __cpuid_count, _xgetbv};
    // SAFETY: CPUID exists on every x86-64 CPU; XGETBV is executed only when CPUID reports
    // OSXSAVE (bit 27 of leaf 1's ECX), i.e. the OS enabled it.
    unsafe {
        let l1 = __cpuid(1);
        let (fma, osxsave, avx) = (
            l1.ecx & (1 << 12) != 0,
            l1.ecx & (1 << 27) != 0,
            l1.ecx & (1 << 28) != 0,
        );
        if !(fma && osxsave && avx) || _xgetbv(0) & 0b110 != 0b110 {
            return false;
        }
        __cpuid(0).eax >= 7 && __cpuid_count(7, 0).ebx & (1 << 5) != 0
    }
}

/// Restores SIGPIPE's default action (ending the process), which Rust's runtime sets to ignore.
#[cfg(unix)]
fn restore_sigpipe() {
    unsafe extern "C" {
        fn signal(signum: i32, handler: usize) -> usize;
    }
    // SIGPIPE is 13 and SIG_DFL 0 on Linux, macOS and the BSDs.
    const SIGPIPE: i32 = 13;
    const SIG_DFL: usize = 0;
    // SAFETY: one signal's disposition reset to its default, before any other thread exists.
    unsafe {
        signal(SIGPIPE, SIG_DFL);
    }
}

fn main() -> ExitCode {
    // .cargo/config.toml builds for x86-64-v3: say so instead of dying on an illegal
    // instruction somewhere later.
    #[cfg(all(target_arch = "x86_64", target_feature = "avx2"))]
    if !cpu_has_avx2_fma() {
        eprintln!(
            "error: this nanoeye was built for x86-64-v3 (AVX2 + FMA) and this CPU lacks them; \
             rebuild with RUSTFLAGS=\"\" (see .cargo/config.toml)"
        );
        return ExitCode::FAILURE;
    }
    // `nanoeye … | head` closes stdout early: end as other Unix tools do, by SIGPIPE, rather
    // than panic in println! on the EPIPE that Rust's ignored SIGPIPE leaves to every write.
    #[cfg(unix)]
    restore_sigpipe();
    nanoeye_alloc::like_cli();
    let _session = dist::init();
    let w = dist::world();
    let cli = match Cli::try_parse() {
        Ok(cli) => cli,
        // Help and version go to stdout as clap writes them; a usage error goes through the
        // same cut of long words as ours (clap echoed a 100 kB value whole).
        Err(e) if !e.use_stderr() => e.exit(),
        Err(e) => {
            let text = match std::io::stderr().is_terminal() {
                true => e.render().ansi().to_string(),
                false => e.render().to_string(),
            };
            let _ = std::io::Write::write_all(
                &mut std::io::stderr().lock(),
                short_words(&text).as_bytes(),
            );
            return ExitCode::from(e.exit_code().clamp(1, 255) as u8);
        }
    };
    if w.is_distributed() && !distributes(&cli.command) {
        // Nothing started yet: every rank stops, rank 0 says why.
        if w.is_root() {
            eprintln!(
                "error: this command runs on one process ({} ranks started): only metalib \
                 sweep, datagen render, optics psf, search train and search rea split across \
                 MPI ranks (docs/mpi.md)",
                w.size()
            );
        }
        return ExitCode::FAILURE;
    }
    match dispatch(cli.command) {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) if w.is_distributed() => {
            // One rank's failure ends every rank: the others may wait on it in a collective.
            // One write of the whole message: stderr is unbuffered, and `eprintln!` writes each
            // formatted piece separately, so another rank's progress line could land inside it.
            let msg = format!(
                "error (rank {} of {}): {}\nthe run is aborted; finished shares stay on disk \
                 and a rerun of the same command resumes them\n",
                w.rank(),
                w.size(),
                short_words(&short_numbers(&format!("{e:#}")))
            );
            let _ = std::io::Write::write_all(&mut std::io::stderr().lock(), msg.as_bytes());
            w.abort(1)
        }
        Err(e) => {
            eprintln!("error: {}", short_words(&short_numbers(&format!("{e:#}"))));
            ExitCode::FAILURE
        }
    }
}

/// `msg` with each decimal number Rust printed in full beyond reason (an f64 of 1e308 is 309
/// digits, 1e-300 has 300 zeros) written in scientific notation: a fraction of more than 21
/// characters or an integer of more than 39 digits (more than any u128), so that counts,
/// seeds and hashes stay as printed.
fn short_numbers(msg: &str) -> String {
    let b = msg.as_bytes();
    let mut out = String::with_capacity(msg.len());
    let (mut i, mut last) = (0, 0);
    while i < b.len() {
        if !b[i].is_ascii_digit()
            || (i > 0 && (b[i - 1].is_ascii_alphanumeric() || b[i - 1] == b'.'))
        {
            i += 1;
            continue;
        }
        let start = i;
        while i < b.len() && b[i].is_ascii_digit() {
            i += 1;
        }
        let mut frac = false;
        if i + 1 < b.len() && b[i] == b'.' && b[i + 1].is_ascii_digit() {
            frac = true;
            i += 1;
            while i < b.len() && b[i].is_ascii_digit() {
                i += 1;
            }
        }
        let long = if frac { i - start > 21 } else { i - start > 39 };
        let next_is_word = i < b.len() && (b[i].is_ascii_alphabetic() || b[i] == b'_');
        if long
            && !next_is_word
            && let Ok(v) = msg[start..i].parse::<f64>()
        {
            out.push_str(&msg[last..start]);
            out.push_str(&format!("{v:e}"));
            last = i;
        }
    }
    out.push_str(&msg[last..]);
    out
}

/// Longest run of non-blank characters an error prints whole: a path or a JSON value given on
/// the command line, not a megabyte of one echoed back.
const WORD_MAX: usize = 400;

/// `msg` with each run of more than [`WORD_MAX`] non-blank characters cut to its first 160 and
/// last 80, the middle replaced by a count of what was left out: a 1 MB `--set` value, a path
/// or a rig's JSON was echoed whole, twice.
fn short_words(msg: &str) -> String {
    let mut out = String::with_capacity(msg.len().min(64 * 1024));
    let mut word: Vec<char> = Vec::new();
    let flush = |word: &mut Vec<char>, out: &mut String| {
        if word.len() > WORD_MAX {
            let n = word.len();
            out.extend(&word[..160]);
            out.push_str(&format!("…[{} characters]…", n - 240));
            out.extend(&word[n - 80..]);
        } else {
            out.extend(word.iter());
        }
        word.clear();
    };
    for c in msg.chars() {
        if c.is_whitespace() {
            flush(&mut word, &mut out);
            out.push(c);
        } else {
            word.push(c);
        }
    }
    flush(&mut word, &mut out);
    out
}

#[cfg(test)]
mod tests {
    use super::{WORD_MAX, short_numbers, short_words};

    /// A long run of non-blank characters is cut to its ends with the count left out; words
    /// up to the limit, blanks and line ends stay as written.
    #[test]
    fn words_echoed_beyond_reason_are_cut_and_no_others() {
        let big = format!("a{}z", "é".repeat(100_000));
        let msg = format!("--set seed={big}: invalid digit\n  in {big}");
        let short = short_words(&msg);
        assert!(short.len() < 2000, "{}", short.len());
        assert!(short.starts_with("--set seed=aé"), "{short}");
        assert!(short.contains("…[99762 characters]…é"), "{short}");
        assert!(short.contains("éz: invalid digit\n  in a"), "{short}");
        let keep = format!("path {} and\t{}", "p".repeat(WORD_MAX), "q");
        assert_eq!(short_words(&keep), keep);
    }

    #[test]
    fn numbers_printed_in_full_beyond_reason_are_shortened_and_no_others() {
        let huge = format!("--pitch-um: at most 189 µm, got {}", 1e308);
        assert!(huge.len() > 300);
        assert_eq!(
            short_numbers(&huge),
            "--pitch-um: at most 189 µm, got 1e308"
        );
        let tiny = format!("got {} m", -1e-300);
        assert_eq!(short_numbers(&tiny), "got -1e-300 m");
        // Counts, seeds, u128 values, hashes and version strings stay as printed.
        for keep in [
            "seed 18446744073709551615, 0.25 µm, 1.5:2:0.5",
            "digest 1234567890123456789012345678901234567890abcdef",
            "x340282366920938463463374607431768211455 and 340282366920938463463374607431768211455",
            "ratio 0.333333333333333",
        ] {
            assert_eq!(short_numbers(keep), keep);
        }
    }
}
