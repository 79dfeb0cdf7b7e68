//! Helpers the compressor's integration tests share.

use wavesplat_codec::volume::{Placement, Volume};

/// The box of `v` as a volume, placed where its first voxel lies: what a region must equal.
pub fn cut(v: &Volume, o: [usize; 3], s: [usize; 3]) -> Volume {
    let channels = v
        .channels()
        .iter()
        .map(|ch| {
            let mut out = Vec::new();
            for z in o[2]..o[2] + s[2] {
                for y in o[1]..o[1] + s[1] {
                    for x in o[0]..o[0] + s[0] {
                        out.push(ch[v.index(x, y, z)]);
                    }
                }
            }
            out
        })
        .collect();
    let b = Volume::new(s, v.spacing(), channels).unwrap();
    match v.placement() {
        Some(p) => b
            .with_placement(Placement {
                origin: p.position(v.spacing(), o.map(|c| c as f64)),
                directions: p.directions,
            })
            .unwrap(),
        None => b,
    }
}
