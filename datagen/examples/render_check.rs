//! Renders a small fixed-seed dataset (envelope and ambiguity sets: varied subjects, gaze, slip
//! and lid states at the rig default 320×200, 4 spp) into a directory, so two builds' outputs
//! can be compared byte for byte with `diff -r` (renderer speed work must not change images).
//!
//! Usage: `cargo run --release -p nanoeye-datagen --example render_check -- OUT_DIR [SEED]`
//! (seed of states, subjects and pixel samples; default 7).

use nanoeye_datagen::render::{DatasetOptions, LayerSpec, RenderSet, SceneSource, write_dataset};
use nanoeye_gaze::Rig;
use std::path::PathBuf;

fn main() {
    let out = PathBuf::from(
        std::env::args()
            .nth(1)
            .expect("usage: render_check OUT_DIR [SEED]"),
    );
    let seed: u64 = std::env::args()
        .nth(2)
        .map_or(7, |s| s.parse().expect("SEED must be an integer"));
    for (set, n, name) in [
        (RenderSet::Envelope, 12, "envelope"),
        (RenderSet::Ambiguity, 2, "ambiguity"),
    ] {
        let opts = DatasetOptions {
            set,
            n,
            seed,
            width_px: 320,
            height_px: 200,
            spp: 4,
            out_dir: out.join(name),
            rig: Rig::default(),
            source: SceneSource::Procedural,
            progress: false,
            layers: LayerSpec::default(),
            blink_fraction: 0.0,
            protocol_grid: nanoeye_datagen::states::PROTOCOL_GRID,
        };
        let s = write_dataset(&opts).expect("render");
        eprintln!("{name}: {s:?}");
    }
}
