//! Cross-crate integration tests of nanoeye; the tests live in `tests/tests/`.
