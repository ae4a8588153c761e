//! Criterion benches: sensor forward and VJP on a 256×256 fine image (1 µm samples).

use criterion::{Criterion, criterion_group, criterion_main};
use faer::Mat;
use nanoeye_sensor::{CmosSensor, Sensor, SensorConfig};
use std::hint::black_box;

fn bench(c: &mut Criterion) {
    let s = CmosSensor::new(SensorConfig::default()).unwrap();
    let img = Mat::from_fn(256, 256, |i, j| 100.0 + ((i * 7 + j * 3) % 50) as f32);
    for p_um in [3.0, 4.5, 9.0] {
        let p = p_um * 1e-6;
        c.bench_function(&format!("sensor_forward_256_p{p_um}um"), |b| {
            b.iter(|| s.forward(black_box(&img), 1e-6, p, 1, 0).unwrap())
        });
        let (dn, tape) = s.forward(&img, 1e-6, p, 1, 0).unwrap();
        let g = Mat::from_fn(dn.nrows(), dn.ncols(), |_, _| 1.0f32);
        c.bench_function(&format!("sensor_vjp_256_p{p_um}um"), |b| {
            b.iter(|| s.vjp(black_box(&tape), black_box(&g)).unwrap())
        });
    }
}

criterion_group!(benches, bench);
criterion_main!(benches);
