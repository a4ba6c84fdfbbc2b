//! The paper's published figures (Crassin et al., JCGT 2015, Table 2 and §5), printed beside
//! ours. Our `city:N` stands in for the paper's game levels: a column of ours is compared
//! with the paper's scene of the nearest polygon count.

/// A scene of the paper's Table 2.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct PaperScene {
    /// Name in the paper.
    pub name: &'static str,
    /// Polygon count.
    pub polygons: u64,
}

/// Table 2's scenes, in its column order.
pub const SCENES: [PaperScene; 6] = [
    PaperScene {
        name: "Cornell Box",
        polygons: 34,
    },
    PaperScene {
        name: "Sponza",
        polygons: 262_000,
    },
    PaperScene {
        name: "Ironworks",
        polygons: 442_000,
    },
    PaperScene {
        name: "Old City",
        polygons: 1_210_000,
    },
    PaperScene {
        name: "Dockside",
        polygons: 1_773_000,
    },
    PaperScene {
        name: "Operation925",
        polygons: 2_598_000,
    },
];

/// The paper's scene nearest to `triangles` (on a log scale): its column index.
pub fn nearest_scene(triangles: u64) -> usize {
    let distance =
        |p: &PaperScene| ((p.polygons as f64).ln() - (triangles.max(1) as f64).ln()).abs();
    SCENES
        .iter()
        .enumerate()
        .min_by(|a, b| distance(a.1).total_cmp(&distance(b.1)))
        .map_or(0, |(i, _)| i)
}

/// Table 2's photon block: (row, one cell per scene of [`SCENES`]).
pub const PHOTONS: [(&str, [&str; 6]); 10] = [
    ("Number of batches", ["1", "13", "7", "9", "8", "9"]),
    (
        "Photons per batch",
        [
            "10,000", "40,000", "100,000", "100,000", "400,000", "160,000",
        ],
    ),
    (
        "Memory footprint",
        ["67 kB", "6.1 MB", "8.3 MB", "5.1 MB", "10.4 MB", "30.22 MB"],
    ),
    (
        "Iteration interval (total)",
        ["6.1 ms", "9.8 ms", "31.8 ms", "20 ms", "32.9 ms", "28.3 ms"],
    ),
    (
        "Photon trace",
        [
            "5.4 ms", "7.8 ms", "26.8 ms", "11.5 ms", "28.6 ms", "19.5 ms",
        ],
    ),
    (
        "Photon compaction",
        ["0.5 ms", "0.9 ms", "2.7 ms", "2.4 ms", "1.6 ms", "2.0 ms"],
    ),
    (
        "GPU to CPU to NIC",
        ["0.2 ms", "1.1 ms", "2.3 ms", "6.1 ms", "2.7 ms", "6.8 ms"],
    ),
    (
        "Server-to-client bandwidth (mean)",
        [
            "16 Mbps", "34 Mbps", "38 Mbps", "25 Mbps", "34 Mbps", "43 Mbps",
        ],
    ),
    (
        "Local device stored photons",
        ["3.4k", "207k", "416k", "257k", "528k", "1511k"],
    ),
    (
        "Local device indirect time",
        ["8 ms", "26 ms", "30 ms", "28 ms", "28 ms", "30.2 ms"],
    ),
];

/// Table 2's irradiance-map block: (row, one cell per scene of [`SCENES`]); "n/a" where the
/// paper could not parametrise the scene.
pub const IRRADIANCE: [(&str, [&str; 6]); 7] = [
    (
        "Number of basis functions",
        ["50", "39,000", "6,300", "n/a", "n/a", "n/a"],
    ),
    (
        "Rays per update",
        ["26k", "20.0M", "1.6M", "n/a", "n/a", "n/a"],
    ),
    (
        "Cloud update time",
        ["7.5 ms", "214 ms", "40 ms", "n/a", "n/a", "n/a"],
    ),
    (
        "Irradiance map texels",
        ["128²", "1024²", "1024²", "n/a", "n/a", "n/a"],
    ),
    (
        "H.264 encode",
        ["≈0.5 ms", "3 ms", "3 ms", "n/a", "n/a", "n/a"],
    ),
    (
        "Server-to-client bandwidth",
        ["0.16 Mbps", "1.5 Mbps", "1.7 Mbps", "n/a", "n/a", "n/a"],
    ),
    (
        "Local device indirect light size",
        ["768 kB", "48 MB", "48 MB", "n/a", "n/a", "n/a"],
    ),
];

/// The paper's Figure 4 (irradiance-map scaling on Ironworks), in words.
pub const IRRADIANCE_SCALING_FIGURE: (&str, &str) = (
    "Figure 4, irradiance maps on Ironworks",
    "per-user latency essentially constant up to 50 users (new users need no server computation); the server's bandwidth grows linearly with users; the network was never saturated",
);

/// Table 2's voxel block: (row, one cell per scene of [`SCENES`]).
pub const VOXELS: [(&str, [&str; 6]); 9] = [
    (
        "Indirect (GI GPU)",
        ["19 ms", "28 ms", "28 ms", "40 ms", "45 ms", "32 ms"],
    ),
    (
        "Light injection",
        ["11 ms", "9 ms", "13 ms", "20 ms", "26 ms", "19 ms"],
    ),
    ("Clear", ["1 ms", "3 ms", "2 ms", "3 ms", "3 ms", "2 ms"]),
    (
        "Gather",
        ["7 ms", "15 ms", "12 ms", "16 ms", "16 ms", "12 ms"],
    ),
    (
        "GI GPU voxel memory",
        ["0.13 GB", "2.6 GB", "2.2 GB", "2.7 GB", "2.0 GB", "2.8 GB"],
    ),
    (
        "GPU-to-GPU bandwidth",
        [
            "2.8 Gbps", "6.7 Gbps", "4.5 Gbps", "6.1 Gbps", "3.7 Gbps", "1.9 Gbps",
        ],
    ),
    VIDEO_FRAMES[0],
    VIDEO_FRAMES[1],
    VIDEO_FRAMES[2],
];

/// Table 2's voxel block, the rows of its final frames streamed as video (the server renders
/// and encodes each client's frame; the client only decodes, about 1 ms at 1080p).
pub const VIDEO_FRAMES: [(&str, [&str; 6]); 3] = [
    (
        "Final frame time",
        ["5 ms", "12 ms", "11 ms", "14 ms", "16 ms", "10 ms"],
    ),
    (
        "H.264 encode (per client)",
        ["4.2 ms", "4.2 ms", "4.2 ms", "4.2 ms", "4.2 ms", "4.2 ms"],
    ),
    (
        "Server-to-client bandwidth (mean)",
        ["3 Mbps", "5 Mbps", "6 Mbps", "6 Mbps", "6 Mbps", "3 Mbps"],
    ),
];

/// The paper's photon operating point on the Cornell box: 10k photons per update,
/// 16 Mbps, 6.1 ms per iteration (GeForce Titan).
pub const PHOTON_OPERATING_POINT: (f64, f64) = (16.0, 6.1);

/// The paper's Figure 5 (photon scaling on Old City), in words: the paper gives no numbers.
pub const SCALING_FIGURE: (&str, &str) = (
    "Figure 5, photons on Old City",
    "good scaling to around 30 users, after which bandwidth limits are reached and latency starts increasing from network congestion",
);

/// The paper's Figure 3 (final frames rendered per client from one voxel grid, Sponza), the
/// figure a cut that renders each client's frame in the cloud is compared with.
pub const VIDEO_SCALING_FIGURE: (&str, &str) = (
    "Figure 3, voxels with final frames per client on Sponza",
    "the common overhead becomes insignificant with many clients; each K5000 serves 5 clients at 30 frames per second (25 at 12 Hz); bandwidth scales linearly with clients",
);

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn our_scenes_map_to_the_paper_scene_of_the_nearest_polygon_count() {
        assert_eq!(SCENES[nearest_scene(32)].name, "Cornell Box");
        assert_eq!(SCENES[nearest_scene(250_104)].name, "Sponza");
        assert_eq!(SCENES[nearest_scene(1_000_032)].name, "Old City");
        assert_eq!(SCENES[nearest_scene(20_000_000)].name, "Operation925");
    }
}
