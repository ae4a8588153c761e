use nanoeye_nets::cost::{mobilenet_v3_large, mobilenet_v3_small};

#[test]
fn mobilenet_v3_counts_match_published() {
    let l = mobilenet_v3_large(224);
    let s = mobilenet_v3_small(224);
    println!("{l:?}\n{s:?}");
    assert_eq!(l.params, 5_483_032);
    assert_eq!(s.params, 2_542_856);
    assert!(
        (l.macs as f64 / 216.6e6 - 1.0).abs() < 0.005,
        "large {}",
        l.macs
    );
    assert!(
        (s.macs as f64 / 56.5e6 - 1.0).abs() < 0.005,
        "small {}",
        s.macs
    );
}
