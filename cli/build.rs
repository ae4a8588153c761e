//! Does nothing. cli/Cargo.toml's `[build-dependencies]` hold a feature pin (syn's features that
//! the `mpi` feature's bindgen turns on); with a build script the pin does not rest on cargo
//! counting the build dependencies of a package that has none (cargo 1.95 did, in its unit
//! graph).

fn main() {
    println!("cargo::rerun-if-changed=build.rs");
}
