//! `nanoeye`: the command-line interface of the nanoeye workspace.
fn main() {}
