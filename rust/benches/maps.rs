//! Map construction cost: all 2,100 view maps of a 4,096-point model, and its
//! parts (visibility, farthest-point sampling), and the encoder's neighbour
//! groups of each map. `cargo bench --bench maps`.

use criterion::{criterion_group, criterion_main, Criterion};
use rayon::prelude::*;

use edgepose_core::{
    compute_maps, farthest_point_sample, features_of_maps, map_neighbours, view_map, viewpoints,
    visible_mask, StandardModel,
};

/// A torus (radii 6 cm and 2 cm): non-convex, so it exercises the z-buffer.
fn torus_model() -> StandardModel {
    let (major, minor, nu, nv) = (0.06f64, 0.02f64, 96usize, 48usize);
    let mut vertices = Vec::new();
    for i in 0..nu {
        for j in 0..nv {
            let (u, v) = (
                i as f64 / nu as f64 * std::f64::consts::TAU,
                j as f64 / nv as f64 * std::f64::consts::TAU,
            );
            let r = major + minor * v.cos();
            vertices.push([r * u.cos(), r * u.sin(), minor * v.sin()]);
        }
    }
    let mut faces = Vec::new();
    for i in 0..nu {
        for j in 0..nv {
            let a = (i * nv + j) as u32;
            let b = (((i + 1) % nu) * nv + j) as u32;
            let c = (((i + 1) % nu) * nv + (j + 1) % nv) as u32;
            let d = (i * nv + (j + 1) % nv) as u32;
            faces.push([a, b, c]);
            faces.push([a, c, d]);
        }
    }
    StandardModel::from_mesh(&vertices, &faces, 4096, 0).expect("valid torus")
}

fn bench_maps(c: &mut Criterion) {
    let model = torus_model();
    let (_, rotations) = viewpoints(2100);
    let mut group = c.benchmark_group("maps");
    group.sample_size(10);
    group.bench_function("all_2100_views_4096_points_m512", |b| {
        b.iter(|| compute_maps(&model, &rotations, 512))
    });
    group.bench_function("visibility_only_2100_views", |b| {
        // On the core's pool, as `compute_maps` is.
        b.iter(|| {
            edgepose_core::threads::install(|| {
                rotations
                    .par_iter()
                    .map(|r| {
                        let r = r.cast::<f32>();
                        let rot = |p: &[f32; 3]| {
                            let v = r * nalgebra::Vector3::new(p[0], p[1], p[2]);
                            [v.x, v.y, v.z]
                        };
                        let p: Vec<[f32; 3]> = model.points.iter().map(rot).collect();
                        let n: Vec<[f32; 3]> = model.normals.iter().map(rot).collect();
                        visible_mask(&p, &n, model.spacing as f32)
                            .iter()
                            .filter(|v| **v)
                            .count()
                    })
                    .sum::<usize>()
            })
        })
    });
    group.finish();

    let one_view = view_map(&model, &rotations[700], 2048);
    let visible: Vec<[f32; 3]> = one_view.points[..one_view.visible.min(2048)].to_vec();
    let mut fps = c.benchmark_group("fps");
    fps.bench_function(format!("{}_to_512", visible.len()), |b| {
        b.iter(|| farthest_point_sample(&visible, 512))
    });
    // Fewer picks than blocks pay for (the second search's voting points):
    // a pass over every point for each pick.
    fps.bench_function(format!("{}_to_160", visible.len()), |b| {
        b.iter(|| farthest_point_sample(&visible, 160))
    });
    fps.finish();

    // The encoder's neighbour groups (128 centres × 16 neighbours) of one map,
    // and its inputs (groups and features, 8 harmonics) for a whole codebook.
    let maps = compute_maps(&model, &rotations, 512);
    let mut groups = c.benchmark_group("neighbour_groups");
    groups.bench_function("one_map_512_points_128x16", |b| {
        b.iter(|| map_neighbours(&maps.points[..512], 128, 16))
    });
    groups.bench_function("features_of_one_map_128x16", |b| {
        b.iter(|| features_of_maps(&maps.points[..512], 512, 128, 16, 8))
    });
    groups.sample_size(10);
    groups.bench_function("features_of_all_2100_maps_128x16", |b| {
        b.iter(|| features_of_maps(&maps.points, 512, 128, 16, 8))
    });
    groups.finish();
}

criterion_group!(benches, bench_maps);
criterion_main!(benches);
