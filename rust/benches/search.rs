//! Query hot path: cosine top-16 over 2,100 codes, verification of 16
//! candidates by 32 keypoints, ICP, segmentation, the support plane, scoring,
//! the flip margin and point-pair votes. `cargo bench --bench search`.

use criterion::{criterion_group, criterion_main, Criterion};
use nalgebra::{Rotation3, Unit, Vector3};

use edgepose_core::flips::{flip_margin, FlipSettings};
use edgepose_core::pairs::{PairSettings, PairTable};
use edgepose_core::rng::SplitMix64;
use edgepose_core::scoring::align_translations;
use edgepose_core::{
    on_support_plane, score_poses, segment, top_k, verify, DepthGrid, ModelIndex, Pinhole, Point3,
    Pose, SceneDepth, ScoreSettings, SegmentSettings, SupportSettings,
};

fn unit_codes(views: usize, dim: usize, rng: &mut SplitMix64) -> Vec<f32> {
    let mut codes: Vec<f32> = (0..views * dim)
        .map(|_| rng.next_f64() as f32 - 0.5)
        .collect();
    for code in codes.chunks_exact_mut(dim) {
        let norm = code.iter().map(|v| v * v).sum::<f32>().sqrt();
        code.iter_mut().for_each(|v| *v /= norm);
    }
    codes
}

/// 4,096 points on a 10 × 6 × 4 cm box surface with outward normals.
fn box_model(rng: &mut SplitMix64) -> (Vec<Point3>, Vec<Point3>) {
    let half = [0.05f32, 0.03, 0.02];
    let mut points = Vec::new();
    let mut normals = Vec::new();
    while points.len() < 4096 {
        let axis = (rng.next_f64() * 3.0) as usize % 3;
        let sign = if rng.next_f64() < 0.5 { -1.0 } else { 1.0 };
        let mut p = [0.0f32; 3];
        for k in 0..3 {
            p[k] = (rng.next_f64() as f32 * 2.0 - 1.0) * half[k];
        }
        p[axis] = sign * half[axis];
        let mut n = [0.0f32; 3];
        n[axis] = sign;
        points.push(p);
        normals.push(n);
    }
    (points, normals)
}

fn bench_search(c: &mut Criterion) {
    let mut rng = SplitMix64::new(1);
    let codes = unit_codes(2100, 64, &mut rng);
    let query = unit_codes(1, 64, &mut rng);
    let (points, normals) = box_model(&mut rng);
    let index = ModelIndex::new(points.clone(), normals);
    let truth = Pose {
        rotation: *Rotation3::from_axis_angle(
            &Unit::new_normalize(Vector3::new(1.0, 2.0, 0.5)),
            0.8,
        )
        .matrix(),
        translation: Vector3::new(0.02, -0.01, 0.6),
    };
    let cloud: Vec<Point3> = points
        .iter()
        .step_by(4)
        .map(|p| {
            let v = truth.apply(p);
            [v.x as f32, v.y as f32, v.z as f32]
        })
        .collect();
    let keypoints: Vec<Point3> = cloud.iter().step_by(32).take(32).cloned().collect();
    let candidates: Vec<Pose> = (0..16)
        .map(|k| Pose {
            rotation: *Rotation3::from_euler_angles(0.0, 0.0, k as f64 * 0.3).matrix()
                * truth.rotation,
            ..truth
        })
        .collect();

    let mut group = c.benchmark_group("query");
    group.bench_function("top16_of_2100_codes", |b| {
        b.iter(|| top_k(&codes, 64, &query, 16))
    });
    group.bench_function("verify_16_candidates_32_keypoints", |b| {
        b.iter(|| verify(&index, &keypoints, &candidates))
    });
    group.bench_function("top16_plus_verify16", |b| {
        b.iter(|| {
            let best = top_k(&codes, 64, &query, 16);
            (best, verify(&index, &keypoints, &candidates))
        })
    });
    let start = Pose {
        rotation: *Rotation3::from_euler_angles(0.05, -0.04, 0.03).matrix() * truth.rotation,
        translation: truth.translation + Vector3::new(0.004, -0.003, 0.002),
    };
    group.bench_function("icp_1024_points_20_iterations", |b| {
        b.iter(|| index.refine(&cloud, start, 20, 0.02))
    });
    // Every 4th model point moved by up to `reach` / 2 along each axis (metres).
    let mut jittered = |reach: f32| -> Vec<Point3> {
        points
            .iter()
            .step_by(4)
            .map(|p| p.map(|v| v + reach * (rng.next_f64() as f32 - 0.5)))
            .collect()
    };
    // What ICP asks 20,000 times an estimate: the nearest model point to a
    // point near the surface (model frame, up to 3 mm off), through the grid
    // of cells (`nearest`) and through the kd-tree alone.
    let near = jittered(0.006);
    group.bench_function("nearest_1024_points_near_surface/grid", |b| {
        b.iter(|| near.iter().map(|q| index.nearest(q).1).sum::<f32>())
    });
    // The same queries at once, as ICP, alignment and scoring ask them.
    group.bench_function("nearest_1024_points_near_surface/grid_batch", |b| {
        b.iter(|| {
            index
                .nearest_each_within(&near, f64::INFINITY)
                .iter()
                .map(|found| found.map_or(0.0, |(_, sq)| sq))
                .sum::<f32>()
        })
    });
    group.bench_function("nearest_1024_points_near_surface/kd_tree", |b| {
        b.iter(|| near.iter().map(|q| index.nearest_in_tree(q).1).sum::<f32>())
    });
    // What candidate alignment and scoring ask of a wrong candidate's
    // keypoints: points up to 1 cm off the surface, within 1 cm.
    let off = jittered(0.02);
    group.bench_function("nearest_1024_points_off_surface_within_1cm/grid", |b| {
        b.iter(|| {
            off.iter()
                .filter_map(|q| index.nearest_within(q, 0.01))
                .count()
        })
    });

    // Real-scene steps: the camera-facing half of the box seen from the
    // truth's camera (about 2,048 points with the spill ring below), and a
    // spilled mask's ring of wall 4 cm behind it.
    let seen: Vec<Point3> = index
        .points()
        .iter()
        .zip(index.normals())
        .filter(|(p, n)| {
            let pc = truth.apply(p);
            let nc = truth.rotation * Vector3::new(n[0] as f64, n[1] as f64, n[2] as f64);
            nc.dot(&pc) < 0.0
        })
        .map(|(p, _)| {
            let v = truth.apply(p);
            [v.x as f32, v.y as f32, v.z as f32]
        })
        .collect();
    let ring: Vec<Point3> = (0..2048 - seen.len().min(2048))
        .map(|i| {
            let a = i as f32 * 0.0061;
            [
                0.02 + 0.075 * a.cos(),
                -0.01 + 0.075 * a.sin(),
                0.64 + 0.0001 * (i % 7) as f32,
            ]
        })
        .collect();
    let scene: Vec<Point3> = seen.iter().chain(&ring).copied().collect();
    group.bench_function(format!("segment_{}_points", scene.len()), |b| {
        b.iter(|| segment(&scene, 0.12, &SegmentSettings::default()))
    });
    // The same without step 3 (steep faces put back): what that step costs.
    let without_steep_faces = SegmentSettings {
        steep_faces: false,
        ..SegmentSettings::default()
    };
    group.bench_function(
        format!("segment_{}_points_no_steep_faces", scene.len()),
        |b| b.iter(|| segment(&scene, 0.12, &without_steep_faces)),
    );
    // The wall behind it as a 640 × 480 frame with the object drawn in: the
    // support plane found around the cloud, and the cloud's points on it.
    let camera = Pinhole {
        fx: 572.4,
        fy: 573.6,
        cx: 325.3,
        cy: 242.0,
    };
    let mut frame = vec![0.64f32; 640 * 480];
    for p in &seen {
        let u = (p[0] as f64 * camera.fx / p[2] as f64 + camera.cx).round() as usize;
        let v = (p[1] as f64 * camera.fy / p[2] as f64 + camera.cy).round() as usize;
        if u < 640 && v < 480 {
            frame[v * 640 + u] = frame[v * 640 + u].min(p[2]);
        }
    }
    let support = SupportSettings::default();
    group.bench_function(
        format!("support_plane_{}_points_640x480", scene.len()),
        |b| b.iter(|| on_support_plane(&scene, &frame, 640, &camera, 1.0, 0.12, &support)),
    );
    let spacing = segment(&scene, 0.12, &SegmentSettings::default()).spacing;
    let settings = ScoreSettings {
        inlier_distance: 0.012,
        free_space_tolerance: 0.0036,
        model_stride: 4,
    };
    group.bench_function("score_16_candidates_32_keypoints_free_space", |b| {
        b.iter(|| {
            let grid = DepthGrid::new(&seen, spacing, 2.0);
            score_poses(&index, &keypoints, &grid, &candidates, &settings)
        })
    });
    // The scene test's window of the frame (estimate given the depth image):
    // the whole 640 × 480 frame, converted to metres once per query.
    group.bench_function("scene_window_640x480", |b| {
        b.iter(|| SceneDepth::from_frame(&frame, [480, 640], [0, 480, 0, 640], 1.0, camera, 2))
    });
    group.bench_function("align_16_candidates_32_keypoints_3_iterations", |b| {
        b.iter(|| align_translations(&index, &keypoints, &candidates, 3, 0.012))
    });
    // The confidence's flip margin at estimate's settings (d = 0.12 m): the
    // pose against itself turned half about each model axis, on 256 seen
    // points, the best screened rival settled by 2 ICP iterations. Most of the
    // `confidence` lap; the turned-pose check reads its rival.
    let half_turns: Vec<Pose> = [Vector3::x_axis(), Vector3::y_axis(), Vector3::z_axis()]
        .iter()
        .map(|axis| Pose {
            rotation: *Rotation3::from_axis_angle(axis, std::f64::consts::PI).matrix(),
            translation: Vector3::zeros(),
        })
        .collect();
    let observed: Vec<Point3> = seen
        .iter()
        .step_by(seen.len().div_ceil(256))
        .copied()
        .collect();
    let flip_settings = FlipSettings {
        align_iterations: 1,
        align_distance: 0.012,
        score: ScoreSettings {
            inlier_distance: 0.0024,
            ..settings
        },
        rival_distance: 0.012,
        rival_points: 64,
        symmetric: false,
        settled: 1,
        settle_iterations: 2,
        settle_distance: 0.012,
    };
    let grid = DepthGrid::new(&seen, spacing, 2.0);
    group.bench_function("flip_margin_3_half_turns_256_points", |b| {
        b.iter(|| {
            flip_margin(
                &index,
                &keypoints,
                &observed,
                &grid,
                &truth,
                1.0,
                &half_turns,
                &flip_settings,
            )
        })
    });
    // Point pairs: the model's table (built once per codebook, on the first
    // doubtful view), and the votes of 160 of the seen points (the default).
    group.bench_function("pair_table_384_model_points", |b| {
        b.iter(|| PairTable::new(index.points(), index.normals()))
    });
    index.pair_table();
    group.bench_function("pair_poses_160_points_stride_2", |b| {
        b.iter(|| index.pair_poses(&seen, &PairSettings::default()))
    });
    group.finish();
}

criterion_group!(benches, bench_search);
criterion_main!(benches);
