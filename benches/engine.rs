//! Criterion benchmarks of the engine (filled in as the engine grows).
use criterion::{criterion_group, criterion_main, Criterion};
use std::hint::black_box;

fn bench_sum(c: &mut Criterion) {
    let v: Vec<f64> = (0..1024).map(|i| i as f64).collect();
    c.bench_function("sum_1024", |b| b.iter(|| exolan::sum(black_box(&v))));
}

criterion_group!(benches, bench_sum);
criterion_main!(benches);
