//! What the synthetic room holds: its six surfaces, the furniture and wall items, their materials
//! and labels, all placed from the seed.
//!
//! The room is the box `[-x/2, x/2] × [-y/2, y/2] × [0, height]` (world z up, floor at 0). The
//! camera orbits near the vertical axis, so furniture stands in the ring between a keep-out disk
//! around that axis and the walls; every floor piece backs onto a wall, turned a little, and no two
//! footprints overlap. A few floor-to-ceiling pilasters come first, so that bare walls have some
//! relief. Wall items (pictures, windows, doors, screens, boards) hang flush on a wall where no tall
//! piece stands in front of them. Pieces with a flat top may carry a prop.

use nalgebra::{Point3, Vector3};

use super::geometry::{Aabb, Shape, to_local, to_world};
use super::rng::Rng;
use super::texture::{Material, Pattern};
use super::{LabelInfo, SceneObject};

/// NYU40 class ids of what the generator produces (0 is NYU40's "unlabelled").
pub(crate) mod label {
    pub(crate) const WALL: u16 = 1;
    pub(crate) const FLOOR: u16 = 2;
    pub(crate) const CABINET: u16 = 3;
    pub(crate) const BED: u16 = 4;
    pub(crate) const CHAIR: u16 = 5;
    pub(crate) const SOFA: u16 = 6;
    pub(crate) const TABLE: u16 = 7;
    pub(crate) const DOOR: u16 = 8;
    pub(crate) const WINDOW: u16 = 9;
    pub(crate) const BOOKSHELF: u16 = 10;
    pub(crate) const PICTURE: u16 = 11;
    pub(crate) const DESK: u16 = 14;
    pub(crate) const DRESSER: u16 = 17;
    pub(crate) const PILLOW: u16 = 18;
    pub(crate) const CEILING: u16 = 22;
    pub(crate) const BOOKS: u16 = 23;
    pub(crate) const TELEVISION: u16 = 25;
    pub(crate) const BOX: u16 = 29;
    pub(crate) const WHITEBOARD: u16 = 30;
    pub(crate) const NIGHT_STAND: u16 = 32;
    pub(crate) const LAMP: u16 = 35;
    pub(crate) const OTHERSTRUCTURE: u16 = 38;
    pub(crate) const OTHERPROP: u16 = 40;
}

/// Every class the generator can produce, with its NYU40 id and name.
pub const SYNTHETIC_LABELS: &[LabelInfo] = &[
    LabelInfo::new(0, "unlabelled"),
    LabelInfo::new(label::WALL, "wall"),
    LabelInfo::new(label::FLOOR, "floor"),
    LabelInfo::new(label::CABINET, "cabinet"),
    LabelInfo::new(label::BED, "bed"),
    LabelInfo::new(label::CHAIR, "chair"),
    LabelInfo::new(label::SOFA, "sofa"),
    LabelInfo::new(label::TABLE, "table"),
    LabelInfo::new(label::DOOR, "door"),
    LabelInfo::new(label::WINDOW, "window"),
    LabelInfo::new(label::BOOKSHELF, "bookshelf"),
    LabelInfo::new(label::PICTURE, "picture"),
    LabelInfo::new(label::DESK, "desk"),
    LabelInfo::new(label::DRESSER, "dresser"),
    LabelInfo::new(label::PILLOW, "pillow"),
    LabelInfo::new(label::CEILING, "ceiling"),
    LabelInfo::new(label::BOOKS, "books"),
    LabelInfo::new(label::TELEVISION, "television"),
    LabelInfo::new(label::BOX, "box"),
    LabelInfo::new(label::WHITEBOARD, "whiteboard"),
    LabelInfo::new(label::NIGHT_STAND, "night stand"),
    LabelInfo::new(label::LAMP, "lamp"),
    LabelInfo::new(label::OTHERSTRUCTURE, "otherstructure"),
    LabelInfo::new(label::OTHERPROP, "otherprop"),
];

/// The name of label `id` ("unlabelled" for an unknown id).
pub(crate) fn label_name(id: u16) -> &'static str {
    SYNTHETIC_LABELS
        .iter()
        .find(|l| l.id == id)
        .map_or("unlabelled", |l| l.name)
}

/// Room surfaces, in the order of their instance ids 1..=6: floor, ceiling, then the walls at
/// x = -x/2, x = +x/2, y = -y/2 and y = +y/2 (faces 2 to 5).
pub(crate) const FLOOR: usize = 0;
pub(crate) const CEILING: usize = 1;

/// One solid of a piece, ready to render.
#[derive(Clone, Debug)]
pub(crate) struct Part {
    pub(crate) shape: Shape,
    pub(crate) aabb: Aabb,
    pub(crate) material: Material,
    pub(crate) label: u16,
    pub(crate) instance: u16,
    /// The piece's own frame, in which its textures are fixed.
    pub(crate) origin: Vector3<f64>,
    pub(crate) cos: f64,
    pub(crate) sin: f64,
}

/// The parts of one piece and their common bounds.
#[derive(Clone, Debug)]
pub(crate) struct Span {
    pub(crate) parts: std::ops::Range<usize>,
    pub(crate) aabb: Aabb,
}

/// The whole generated content of a room.
#[derive(Clone, Debug)]
pub(crate) struct Layout {
    pub(crate) min: Vector3<f64>,
    pub(crate) max: Vector3<f64>,
    /// Materials of the six room surfaces (see [`FLOOR`] and [`CEILING`]; walls are 2 to 5).
    pub(crate) surfaces: [Material; 6],
    pub(crate) parts: Vec<Part>,
    /// One per piece, in the order of `objects[6..]`.
    pub(crate) spans: Vec<Span>,
    pub(crate) objects: Vec<SceneObject>,
}

impl Layout {
    /// The label of room surface `face`.
    pub(crate) fn surface_label(face: usize) -> u16 {
        match face {
            FLOOR => label::FLOOR,
            CEILING => label::CEILING,
            _ => label::WALL,
        }
    }

    /// The instance id of room surface `face`.
    pub(crate) fn surface_instance(face: usize) -> u16 {
        face as u16 + 1
    }

    /// The room of `size` furnished with up to `count` pieces from `seed`, keeping the disk of
    /// radius `keepout` around the vertical axis free.
    pub(crate) fn generate(seed: u64, size: [f64; 3], count: usize, keepout: f64) -> Self {
        let mut rng = Rng::new(seed, 0x6c61_796f_7574);
        let half = Vector3::new(size[0] / 2.0, size[1] / 2.0, size[2]);
        let surfaces = room_materials(&mut rng);
        let objects = (0..6)
            .map(|face| {
                let (mut min, mut max) = (
                    Vector3::new(-half.x, -half.y, 0.0),
                    Vector3::new(half.x, half.y, half.z),
                );
                match face {
                    FLOOR => max.z = 0.0,
                    CEILING => min.z = half.z,
                    2 => max.x = -half.x,
                    3 => min.x = half.x,
                    4 => max.y = -half.y,
                    _ => min.y = half.y,
                }
                let label = Self::surface_label(face);
                SceneObject {
                    instance: Self::surface_instance(face),
                    label,
                    name: label_name(label),
                    min: Point3::from(min),
                    max: Point3::from(max),
                }
            })
            .collect();
        let mut layout = Self {
            min: Vector3::new(-half.x, -half.y, 0.0),
            max: Vector3::new(half.x, half.y, half.z),
            surfaces,
            parts: Vec::new(),
            spans: Vec::new(),
            objects,
        };
        let mut placer = Placer {
            half,
            keepout,
            floor: Vec::new(),
            high: Default::default(),
        };
        // Architecture first: a few floor-to-ceiling pilasters give bare walls some relief (in
        // addition to the `count` pieces).
        let pilasters = std::iter::repeat_n(Kind::Pilaster, 3 + rng.below(3));
        for kind in pilasters.chain(catalogue(&mut rng, count)) {
            for _attempt in 0..40 {
                let design = design(kind, &mut rng, half.z);
                if let Some(at) = placer.place(&design, &mut rng) {
                    layout.add(&design.parts, design.label, &at);
                    if let Some(top) = design.top
                        && rng.chance(0.75)
                    {
                        layout.add_prop(&top, &at, &mut rng);
                    }
                    break;
                }
            }
        }
        layout
    }

    /// Keeps the room surfaces and the pieces for which `keep(instance)` holds, renumbering
    /// instances so that they stay the position in `objects` plus one.
    pub(crate) fn retain_pieces(&mut self, keep: impl Fn(u16) -> bool) {
        let old_parts = std::mem::take(&mut self.parts);
        let old_spans = std::mem::take(&mut self.spans);
        let old_objects = std::mem::take(&mut self.objects);
        let (surfaces, pieces) = old_objects.split_at(6.min(old_objects.len()));
        self.objects = surfaces.to_vec();
        for (span, object) in old_spans.into_iter().zip(pieces) {
            if !keep(object.instance) {
                continue;
            }
            let instance = self.objects.len() as u16 + 1;
            let first = self.parts.len();
            for part in &old_parts[span.parts.clone()] {
                self.parts.push(Part {
                    instance,
                    ..part.clone()
                });
            }
            self.spans.push(Span {
                parts: first..self.parts.len(),
                aabb: span.aabb,
            });
            self.objects.push(SceneObject {
                instance,
                ..object.clone()
            });
        }
    }

    /// Adds a piece made of `parts` (in its own frame) at `at`.
    fn add(&mut self, parts: &[(Shape, Material, u16)], label: u16, at: &Placement) {
        let instance = self.objects.len() as u16 + 1;
        let first = self.parts.len();
        let mut aabb = Aabb::empty();
        for (shape, material, part_label) in parts {
            let shape = at.apply(shape);
            let part_aabb = shape.aabb();
            aabb = aabb.union(&part_aabb);
            self.parts.push(Part {
                shape,
                aabb: part_aabb,
                material: *material,
                label: *part_label,
                instance,
                origin: at.origin,
                cos: at.yaw.cos(),
                sin: at.yaw.sin(),
            });
        }
        self.spans.push(Span {
            parts: first..self.parts.len(),
            aabb,
        });
        self.objects.push(SceneObject {
            instance,
            label,
            name: label_name(label),
            min: Point3::from(aabb.min),
            max: Point3::from(aabb.max),
        });
    }

    /// Puts a small prop on the flat top of the piece just placed at `at`.
    fn add_prop(&mut self, top: &Top, at: &Placement, rng: &mut Rng) {
        let (parts, label, half) = prop(rng, top.z);
        let (mx, my) = (top.hx - half - 0.03, top.hy - half - 0.03);
        if mx < 0.0 || my < 0.0 {
            return;
        }
        let local = Vector3::new(rng.range(-mx, mx), rng.range(-my, my), 0.0);
        let prop_at = Placement {
            origin: at.origin + to_world(&local, at.yaw.cos(), at.yaw.sin()),
            yaw: at.yaw + rng.range(-0.6, 0.6),
        };
        self.add(&parts, label, &prop_at);
    }
}

/// Where a piece goes: its frame origin (floor point under its footprint centre) and yaw.
#[derive(Clone, Copy, Debug)]
struct Placement {
    origin: Vector3<f64>,
    yaw: f64,
}

impl Placement {
    /// `shape`, given in the piece's frame, in world coordinates.
    fn apply(&self, shape: &Shape) -> Shape {
        let (c, s) = (self.yaw.cos(), self.yaw.sin());
        let world = |p: &Vector3<f64>| self.origin + to_world(p, c, s);
        match *shape {
            Shape::Cuboid {
                centre,
                cos,
                sin,
                half,
            } => Shape::Cuboid {
                centre: world(&centre),
                cos: c * cos - s * sin,
                sin: s * cos + c * sin,
                half,
            },
            Shape::Cylinder { x, y, z0, z1, r } => {
                let p = world(&Vector3::new(x, y, 0.0));
                Shape::Cylinder {
                    x: p.x,
                    y: p.y,
                    z0: z0 + self.origin.z,
                    z1: z1 + self.origin.z,
                    r,
                }
            }
            Shape::Sphere { centre, r } => Shape::Sphere {
                centre: world(&centre),
                r,
            },
        }
    }
}

/// The flat top of a piece, in its frame: half extents and height.
#[derive(Clone, Copy, Debug)]
struct Top {
    hx: f64,
    hy: f64,
    z: f64,
}

/// How a piece is mounted.
#[derive(Clone, Copy, Debug, PartialEq)]
enum Mount {
    /// Stands on the floor, back to a wall, turned by up to `jitter` radians, `gap` from the wall.
    Floor { jitter: f64, gap: (f64, f64) },
    /// Hangs flush on a wall (its parts already carry their height).
    Wall,
    /// A door: flush on a wall, and the floor in front of it stays free.
    Door,
}

/// A piece before placement: parts in its own frame (x along the wall, y into the room, z up,
/// origin on the floor under the footprint centre).
#[derive(Clone, Debug)]
struct Design {
    label: u16,
    /// Footprint half extents (x along the wall, y away from it).
    hx: f64,
    hy: f64,
    height: f64,
    mount: Mount,
    parts: Vec<(Shape, Material, u16)>,
    top: Option<Top>,
}

/// What has been placed so far, for the overlap tests.
struct Placer {
    half: Vector3<f64>,
    keepout: f64,
    /// Floor footprints (x/y bounds), including the free zone in front of doors.
    floor: Vec<Aabb>,
    /// Per wall, the intervals along it taken above 0.95 m (by tall pieces and wall items).
    high: [Vec<(f64, f64)>; 4],
}

/// Height above which a floor piece hides the wall behind it.
const TALL: f64 = 0.95;

impl Placer {
    /// A free spot for `design`, if a random try finds one.
    fn place(&mut self, design: &Design, rng: &mut Rng) -> Option<Placement> {
        let wall = rng.below(4);
        // Inward normal, direction along the wall, half length, and the wall's distance from the
        // axis.
        let (normal, along, half_length, distance): (Vector3<f64>, Vector3<f64>, f64, f64) =
            match wall {
                0 => (Vector3::x(), -Vector3::y(), self.half.y, self.half.x),
                1 => (-Vector3::x(), Vector3::y(), self.half.y, self.half.x),
                2 => (Vector3::y(), Vector3::x(), self.half.x, self.half.y),
                _ => (-Vector3::y(), -Vector3::x(), self.half.x, self.half.y),
            };
        // Local +y is the inward normal, local +x runs along the wall.
        let wall_yaw = along.y.atan2(along.x);
        let (jitter, gap) = match design.mount {
            Mount::Floor { jitter, gap } => (rng.range(-jitter, jitter), rng.range(gap.0, gap.1)),
            Mount::Wall | Mount::Door => (0.0, 0.0),
        };
        let (c, s) = (jitter.cos().abs(), jitter.sin().abs());
        let ex = design.hx * c + design.hy * s;
        let ey = design.hx * s + design.hy * c;
        let margin = if matches!(design.mount, Mount::Floor { .. }) {
            0.03
        } else {
            0.1
        };
        let reach = half_length - ex - margin;
        if reach <= 0.0 {
            return None;
        }
        let along_wall = rng.range(-reach, reach);
        let origin = -normal * distance + along * along_wall + normal * (gap + ey);
        let at = Placement {
            origin,
            yaw: wall_yaw + jitter,
        };
        let footprint = Aabb {
            min: Vector3::new(
                origin.x - ex_world(ex, ey, &along),
                origin.y - ey_world(ex, ey, &along),
                0.0,
            ),
            max: Vector3::new(
                origin.x + ex_world(ex, ey, &along),
                origin.y + ey_world(ex, ey, &along),
                design.height,
            ),
        };
        let interval = (along_wall - ex - 0.05, along_wall + ex + 0.05);
        let high_free = self.high[wall]
            .iter()
            .all(|&(a, b)| interval.1 <= a || interval.0 >= b);
        match design.mount {
            Mount::Floor { .. } => {
                let inside = footprint.min.x >= -self.half.x + 0.01
                    && footprint.max.x <= self.half.x - 0.01
                    && footprint.min.y >= -self.half.y + 0.01
                    && footprint.max.y <= self.half.y - 0.01;
                if !inside
                    || self.footprint_distance(&at, design) < self.keepout
                    || self.overlaps_floor(&footprint)
                    || (design.height > TALL && !high_free)
                {
                    return None;
                }
                self.floor.push(footprint);
                if design.height > TALL {
                    self.high[wall].push(interval);
                }
            }
            Mount::Wall => {
                if !high_free {
                    return None;
                }
                self.high[wall].push(interval);
            }
            Mount::Door => {
                // The door leaf plus the floor it swings over.
                let swing = 0.9;
                let zone = Aabb {
                    min: footprint.min.inf(&(footprint.min + normal * swing)),
                    max: footprint.max.sup(&(footprint.max + normal * swing)),
                };
                if !high_free || self.overlaps_floor(&zone) {
                    return None;
                }
                self.floor.push(zone);
                self.high[wall].push(interval);
            }
        }
        Some(at)
    }

    /// Distance from the vertical axis to the nearest point of the design's footprint at `at`.
    fn footprint_distance(&self, at: &Placement, design: &Design) -> f64 {
        let axis = to_local(&(-at.origin), at.yaw.cos(), at.yaw.sin());
        let dx = axis.x.abs() - design.hx;
        let dy = axis.y.abs() - design.hy;
        (dx.max(0.0).powi(2) + dy.max(0.0).powi(2)).sqrt()
    }

    fn overlaps_floor(&self, footprint: &Aabb) -> bool {
        const MARGIN: f64 = 0.08;
        self.floor.iter().any(|other| {
            footprint.min.x < other.max.x + MARGIN
                && footprint.max.x > other.min.x - MARGIN
                && footprint.min.y < other.max.y + MARGIN
                && footprint.max.y > other.min.y - MARGIN
        })
    }
}

/// World x half extent of a footprint with half extents `ex` along and `ey` across a wall that
/// runs along `along` (an axis direction).
fn ex_world(ex: f64, ey: f64, along: &Vector3<f64>) -> f64 {
    if along.x.abs() > 0.5 { ex } else { ey }
}

/// World y half extent, see [`ex_world`].
fn ey_world(ex: f64, ey: f64, along: &Vector3<f64>) -> f64 {
    if along.x.abs() > 0.5 { ey } else { ex }
}

/// The kinds of piece.
#[derive(Clone, Copy, Debug, PartialEq, Eq)]
enum Kind {
    Pilaster,
    Bed,
    Sofa,
    Table,
    Desk,
    Bookshelf,
    Cabinet,
    Dresser,
    NightStand,
    Chair,
    Lamp,
    Crate,
    Ball,
    Door,
    Window,
    Picture,
    Television,
    Whiteboard,
}

/// The pieces to try, in order: the common classes first (big ones first, so they find room),
/// then random extras, `count` in all.
fn catalogue(rng: &mut Rng, count: usize) -> Vec<Kind> {
    use Kind::*;
    let core = [
        Bed, Sofa, Table, Bookshelf, Cabinet, Chair, Lamp, Door, Window, Picture,
    ];
    let extras = [
        Chair, Crate, Ball, Picture, NightStand, Dresser, Desk, Television, Whiteboard, Cabinet,
        Lamp,
    ];
    let mut kinds: Vec<Kind> = core.iter().copied().take(count).collect();
    while kinds.len() < count {
        kinds.push(rng.pick(&extras).unwrap_or(Chair));
    }
    kinds
}

/// Colours (linear RGB in 0..1).
mod palette {
    pub(super) const WOOD: [[[f64; 3]; 2]; 4] = [
        [[0.55, 0.36, 0.20], [0.36, 0.21, 0.10]],
        [[0.78, 0.62, 0.42], [0.58, 0.42, 0.25]],
        [[0.42, 0.25, 0.16], [0.25, 0.13, 0.08]],
        [[0.86, 0.74, 0.55], [0.66, 0.52, 0.34]],
    ];
    pub(super) const FABRIC: [[f64; 3]; 8] = [
        [0.62, 0.16, 0.14],
        [0.18, 0.30, 0.55],
        [0.24, 0.45, 0.28],
        [0.55, 0.52, 0.48],
        [0.80, 0.62, 0.20],
        [0.40, 0.22, 0.45],
        [0.15, 0.15, 0.17],
        [0.85, 0.80, 0.70],
    ];
    pub(super) const PAINT: [[f64; 3]; 7] = [
        [0.90, 0.89, 0.85],
        [0.80, 0.84, 0.88],
        [0.88, 0.82, 0.70],
        [0.72, 0.82, 0.74],
        [0.86, 0.74, 0.72],
        [0.60, 0.63, 0.66],
        [0.35, 0.42, 0.50],
    ];
    pub(super) const BRIGHT: [[f64; 3]; 8] = [
        [0.92, 0.22, 0.16],
        [0.10, 0.35, 0.80],
        [0.98, 0.80, 0.10],
        [0.10, 0.60, 0.30],
        [0.95, 0.95, 0.92],
        [0.08, 0.08, 0.10],
        [0.95, 0.50, 0.10],
        [0.55, 0.20, 0.65],
    ];
}

fn pick(rng: &mut Rng, colours: &[[f64; 3]]) -> [f64; 3] {
    rng.pick(colours).unwrap_or([0.5; 3])
}

/// Two clearly different colours from `colours`.
fn pick_two(rng: &mut Rng, colours: &[[f64; 3]]) -> ([f64; 3], [f64; 3]) {
    let a = rng.below(colours.len());
    let b = (a + 1 + rng.below(colours.len().saturating_sub(1).max(1))) % colours.len();
    (
        colours.get(a).copied().unwrap_or([0.2; 3]),
        colours.get(b).copied().unwrap_or([0.8; 3]),
    )
}

/// `c` scaled towards black by `k` (0..1).
fn darker(c: [f64; 3], k: f64) -> [f64; 3] {
    c.map(|x| x * k)
}

fn wood(rng: &mut Rng) -> Material {
    let [a, b] = rng.pick(&palette::WOOD).unwrap_or(palette::WOOD[0]);
    Material::new(
        a,
        b,
        Pattern::Wood {
            rings: rng.range(18.0, 35.0),
        },
        rng,
    )
}

fn fabric(rng: &mut Rng) -> Material {
    let a = pick(rng, &palette::FABRIC);
    let pattern = Pattern::Fabric {
        weave: rng.range(0.035, 0.06),
    };
    Material::new(darker(a, 0.7), a, pattern, rng)
}

fn paint(rng: &mut Rng) -> Material {
    let a = pick(rng, &palette::PAINT);
    Material::new(
        darker(a, 0.8),
        a,
        Pattern::Plaster {
            wavelength: rng.range(0.12, 0.3),
        },
        rng,
    )
}

fn metal(rng: &mut Rng) -> Material {
    let g = rng.range(0.25, 0.6);
    Material::new(
        [g * 0.8; 3],
        [g * 1.2; 3],
        Pattern::Stripes {
            period: rng.range(0.05, 0.09),
            axis: 2,
        },
        rng,
    )
}

/// A high-contrast pattern (pictures, screens, balls, book spines).
fn poster(rng: &mut Rng) -> Material {
    let (a, b) = pick_two(rng, &palette::BRIGHT);
    let pattern = match rng.below(4) {
        0 => Pattern::Checker {
            size: rng.range(0.05, 0.1),
        },
        1 => Pattern::Stripes {
            period: rng.range(0.05, 0.12),
            axis: rng.below(3),
        },
        _ => Pattern::Blobs {
            wavelength: rng.range(0.08, 0.2),
        },
    };
    Material::new(a, b, pattern, rng)
}

fn room_materials(rng: &mut Rng) -> [Material; 6] {
    let floor = match rng.below(3) {
        0 => {
            let [a, b] = rng.pick(&palette::WOOD).unwrap_or(palette::WOOD[0]);
            Material::new(
                a,
                b,
                Pattern::Planks {
                    width: rng.range(0.12, 0.2),
                    length: rng.range(0.8, 1.4),
                },
                rng,
            )
        }
        1 => {
            let (a, b) = pick_two(rng, &palette::PAINT);
            Material::new(
                a,
                b,
                Pattern::Tiles {
                    size: rng.range(0.3, 0.5),
                },
                rng,
            )
        }
        _ => {
            let (a, b) = pick_two(rng, &palette::PAINT);
            Material::new(
                darker(a, 0.6),
                b,
                Pattern::Checker {
                    size: rng.range(0.25, 0.4),
                },
                rng,
            )
        }
    };
    let ceiling_colour = [0.93, 0.92, 0.9];
    let ceiling = Material::new(
        darker(ceiling_colour, 0.8),
        ceiling_colour,
        Pattern::Tiles {
            size: rng.range(0.5, 0.65),
        },
        rng,
    );
    let wall = |axis: usize, rng: &mut Rng| {
        let (a, b) = pick_two(rng, &palette::PAINT);
        let pattern = match rng.below(4) {
            0 => Pattern::Plaster {
                wavelength: rng.range(0.2, 0.4),
            },
            1 => Pattern::Stripes {
                period: rng.range(0.1, 0.22),
                axis,
            },
            2 => Pattern::Tiles {
                size: rng.range(0.15, 0.3),
            },
            _ => Pattern::Blobs {
                wavelength: rng.range(0.25, 0.5),
            },
        };
        Material::new(a, b, pattern, rng)
    };
    // Walls at x = ±x/2 run along y: their stripes go across y (axis 1), and the other way round.
    [
        floor,
        ceiling,
        wall(1, rng),
        wall(1, rng),
        wall(0, rng),
        wall(0, rng),
    ]
}

/// A box part: centre and half extents in the piece's frame.
fn cuboid(
    centre: [f64; 3],
    half: [f64; 3],
    material: Material,
    label: u16,
) -> (Shape, Material, u16) {
    (
        Shape::cuboid(Vector3::from(centre), 0.0, Vector3::from(half)),
        material,
        label,
    )
}

fn cylinder(
    x: f64,
    y: f64,
    z: (f64, f64),
    r: f64,
    material: Material,
    label: u16,
) -> (Shape, Material, u16) {
    (
        Shape::Cylinder {
            x,
            y,
            z0: z.0,
            z1: z.1,
            r,
        },
        material,
        label,
    )
}

fn sphere(centre: [f64; 3], r: f64, material: Material, label: u16) -> (Shape, Material, u16) {
    (
        Shape::Sphere {
            centre: Vector3::from(centre),
            r,
        },
        material,
        label,
    )
}

/// A random piece of `kind` for a room of height `room_height`.
fn design(kind: Kind, rng: &mut Rng, room_height: f64) -> Design {
    let floor = |jitter: f64, gap: (f64, f64)| Mount::Floor { jitter, gap };
    let mut parts = Vec::new();
    let (label, hx, hy, height, mount, top) = match kind {
        Kind::Table | Kind::Desk => {
            let (w, d, h) = (
                rng.range(1.0, 1.6),
                rng.range(0.6, 0.85),
                rng.range(0.72, 0.78),
            );
            let (top_mat, leg_mat) = (
                wood(rng),
                if rng.chance(0.5) {
                    wood(rng)
                } else {
                    metal(rng)
                },
            );
            let label = if kind == Kind::Table {
                label::TABLE
            } else {
                label::DESK
            };
            parts.push(cuboid(
                [0.0, 0.0, h - 0.02],
                [w / 2.0, d / 2.0, 0.02],
                top_mat,
                label,
            ));
            let (lx, ly) = (w / 2.0 - 0.07, d / 2.0 - 0.07);
            for (sx, sy) in [(-1.0, -1.0), (1.0, -1.0), (-1.0, 1.0), (1.0, 1.0)] {
                if kind == Kind::Desk && sx > 0.0 {
                    continue;
                }
                parts.push(cylinder(
                    sx * lx,
                    sy * ly,
                    (0.0, h - 0.04),
                    0.03,
                    leg_mat,
                    label,
                ));
            }
            if kind == Kind::Desk {
                // A drawer block under the right-hand side, with two drawer fronts.
                let bw = (0.3 * w).max(0.35) / 2.0;
                let body = wood(rng);
                parts.push(cuboid(
                    [w / 2.0 - bw, 0.0, (h - 0.04) / 2.0],
                    [bw, d / 2.0 - 0.02, (h - 0.04) / 2.0],
                    body,
                    label,
                ));
                let front = wood(rng);
                for k in 0..2 {
                    let zc = (h - 0.04) * (0.3 + 0.45 * f64::from(k));
                    parts.push(cuboid(
                        [w / 2.0 - bw, d / 2.0 - 0.015, zc],
                        [bw - 0.03, 0.008, 0.13],
                        front,
                        label,
                    ));
                }
            }
            let top = Top {
                hx: w / 2.0,
                hy: d / 2.0,
                z: h,
            };
            (
                label,
                w / 2.0,
                d / 2.0,
                h,
                floor(0.15, (0.05, 0.2)),
                Some(top),
            )
        }
        Kind::Chair => {
            let s = rng.range(0.42, 0.5);
            let seat_h = rng.range(0.43, 0.48);
            let (seat, frame) = (
                fabric(rng),
                if rng.chance(0.5) {
                    wood(rng)
                } else {
                    metal(rng)
                },
            );
            let half = s / 2.0;
            parts.push(cuboid(
                [0.0, 0.0, seat_h - 0.025],
                [half, half, 0.025],
                seat,
                label::CHAIR,
            ));
            for (sx, sy) in [(-1.0, -1.0), (1.0, -1.0), (-1.0, 1.0), (1.0, 1.0)] {
                parts.push(cuboid(
                    [
                        sx * (half - 0.025),
                        sy * (half - 0.025),
                        (seat_h - 0.05) / 2.0,
                    ],
                    [0.02, 0.02, (seat_h - 0.05) / 2.0],
                    frame,
                    label::CHAIR,
                ));
            }
            let back_h = rng.range(0.38, 0.48);
            parts.push(cuboid(
                [0.0, -half + 0.02, seat_h + back_h / 2.0],
                [half, 0.02, back_h / 2.0],
                frame,
                label::CHAIR,
            ));
            (
                label::CHAIR,
                half,
                half,
                seat_h + back_h,
                floor(0.45, (0.05, 0.3)),
                None,
            )
        }
        Kind::Sofa => {
            let (w, d) = (rng.range(1.6, 2.2), rng.range(0.8, 0.95));
            let cloth = fabric(rng);
            let base_h = 0.42;
            parts.push(cuboid(
                [0.0, 0.0, base_h / 2.0],
                [w / 2.0, d / 2.0, base_h / 2.0],
                cloth,
                label::SOFA,
            ));
            parts.push(cuboid(
                [0.0, -d / 2.0 + 0.11, base_h + 0.22],
                [w / 2.0, 0.11, 0.22],
                cloth,
                label::SOFA,
            ));
            for sx in [-1.0, 1.0] {
                parts.push(cuboid(
                    [sx * (w / 2.0 - 0.09), 0.0, base_h + 0.1],
                    [0.09, d / 2.0, 0.1],
                    cloth,
                    label::SOFA,
                ));
            }
            let cushions = 2 + rng.below(2);
            let cushion = fabric(rng);
            let span = w - 0.4;
            for k in 0..cushions {
                let x = -span / 2.0 + span * (k as f64 + 0.5) / cushions as f64;
                parts.push(cuboid(
                    [x, -d / 2.0 + 0.22 + 0.06, base_h + 0.2],
                    [0.2, 0.06, 0.19],
                    cushion,
                    label::PILLOW,
                ));
            }
            (
                label::SOFA,
                w / 2.0,
                d / 2.0,
                base_h + 0.44,
                floor(0.05, (0.03, 0.1)),
                None,
            )
        }
        Kind::Bed => {
            let (l, w) = (rng.range(1.9, 2.0), rng.range(0.9, 1.0));
            let (frame, mattress, pillow) = (wood(rng), fabric(rng), fabric(rng));
            parts.push(cuboid(
                [0.0, 0.0, 0.15],
                [l / 2.0, w / 2.0, 0.15],
                frame,
                label::BED,
            ));
            parts.push(cuboid(
                [0.03, 0.0, 0.4],
                [l / 2.0 - 0.05, w / 2.0 - 0.02, 0.1],
                mattress,
                label::BED,
            ));
            parts.push(cuboid(
                [-l / 2.0 + 0.03, 0.0, 0.45],
                [0.03, w / 2.0, 0.45],
                frame,
                label::BED,
            ));
            parts.push(cuboid(
                [-l / 2.0 + 0.3, 0.0, 0.57],
                [0.18, w / 2.0 - 0.12, 0.07],
                pillow,
                label::PILLOW,
            ));
            (
                label::BED,
                l / 2.0,
                w / 2.0,
                0.9,
                floor(0.03, (0.02, 0.06)),
                None,
            )
        }
        Kind::Cabinet | Kind::Dresser | Kind::NightStand => {
            let (label, w, d, h, drawers) = match kind {
                Kind::Cabinet => (
                    label::CABINET,
                    rng.range(0.6, 1.2),
                    rng.range(0.4, 0.6),
                    rng.range(0.8, 1.2),
                    0,
                ),
                Kind::Dresser => (
                    label::DRESSER,
                    rng.range(0.9, 1.4),
                    rng.range(0.45, 0.55),
                    rng.range(0.8, 0.95),
                    3,
                ),
                _ => (
                    label::NIGHT_STAND,
                    rng.range(0.4, 0.55),
                    rng.range(0.35, 0.45),
                    rng.range(0.5, 0.6),
                    1,
                ),
            };
            let body = if rng.chance(0.6) {
                wood(rng)
            } else {
                paint(rng)
            };
            let handle = metal(rng);
            parts.push(cuboid(
                [0.0, 0.0, h / 2.0],
                [w / 2.0, d / 2.0, h / 2.0],
                body,
                label,
            ));
            if drawers == 0 {
                // Two doors: a seam is the texture's business; the handles are upright cylinders.
                for sx in [-1.0, 1.0] {
                    parts.push(cylinder(
                        sx * 0.06,
                        d / 2.0 + 0.025,
                        (h * 0.55, h * 0.55 + 0.14),
                        0.012,
                        handle,
                        label,
                    ));
                }
            } else {
                let front = wood(rng);
                let dh = (h - 0.08) / f64::from(drawers);
                for k in 0..drawers {
                    let zc = 0.04 + dh * (f64::from(k) + 0.5);
                    parts.push(cuboid(
                        [0.0, d / 2.0 + 0.008, zc],
                        [w / 2.0 - 0.03, 0.008, dh / 2.0 - 0.015],
                        front,
                        label,
                    ));
                    parts.push(cylinder(
                        0.0,
                        d / 2.0 + 0.03,
                        (zc - 0.03, zc + 0.03),
                        0.012,
                        handle,
                        label,
                    ));
                }
            }
            let top = Top {
                hx: w / 2.0,
                hy: d / 2.0,
                z: h,
            };
            (
                label,
                w / 2.0,
                d / 2.0 + 0.04,
                h,
                floor(0.05, (0.02, 0.06)),
                Some(top),
            )
        }
        Kind::Bookshelf => {
            let (w, d) = (rng.range(0.8, 1.2), rng.range(0.28, 0.38));
            let h = rng.range(1.6, 2.0).min(room_height - 0.2);
            let board = if rng.chance(0.7) {
                wood(rng)
            } else {
                paint(rng)
            };
            let t = 0.02;
            parts.push(cuboid(
                [-w / 2.0 + t / 2.0, 0.0, h / 2.0],
                [t / 2.0, d / 2.0, h / 2.0],
                board,
                label::BOOKSHELF,
            ));
            parts.push(cuboid(
                [w / 2.0 - t / 2.0, 0.0, h / 2.0],
                [t / 2.0, d / 2.0, h / 2.0],
                board,
                label::BOOKSHELF,
            ));
            parts.push(cuboid(
                [0.0, -d / 2.0 + 0.005, h / 2.0],
                [w / 2.0 - t, 0.005, h / 2.0],
                board,
                label::BOOKSHELF,
            ));
            let levels = 4 + rng.below(2);
            let pitch = (h - t) / levels as f64;
            for k in 0..=levels {
                let z = t / 2.0 + pitch * k as f64;
                parts.push(cuboid(
                    [0.0, 0.0, z],
                    [w / 2.0 - t, d / 2.0, t / 2.0],
                    board,
                    label::BOOKSHELF,
                ));
                if k == levels {
                    break;
                }
                // Two or three blocks of books per shelf, leaving gaps.
                let inner = w - 2.0 * t;
                let mut x = -inner / 2.0 + rng.range(0.0, 0.1);
                for _ in 0..(2 + rng.below(2)) {
                    let bw = rng.range(0.12, 0.3);
                    if x + bw > inner / 2.0 - 0.01 {
                        break;
                    }
                    let bh = rng.range(0.5, 0.85) * (pitch - t);
                    let bd = rng.range(0.6, 0.9) * (d - 0.02) / 2.0;
                    let (a, b) = pick_two(rng, &palette::BRIGHT);
                    let spines = Material::new(
                        a,
                        b,
                        Pattern::Stripes {
                            period: rng.range(0.03, 0.06),
                            axis: 0,
                        },
                        rng,
                    );
                    parts.push(cuboid(
                        [x + bw / 2.0, -d / 2.0 + 0.01 + bd, z + t / 2.0 + bh / 2.0],
                        [bw / 2.0, bd, bh / 2.0],
                        spines,
                        label::BOOKS,
                    ));
                    x += bw + rng.range(0.03, 0.15);
                }
            }
            (
                label::BOOKSHELF,
                w / 2.0,
                d / 2.0,
                h,
                floor(0.03, (0.02, 0.05)),
                None,
            )
        }
        Kind::Lamp => {
            let h = rng.range(1.4, 1.7);
            let (base, shade) = (metal(rng), fabric(rng));
            parts.push(cylinder(0.0, 0.0, (0.0, 0.03), 0.14, base, label::LAMP));
            parts.push(cylinder(
                0.0,
                0.0,
                (0.03, h - 0.22),
                0.015,
                base,
                label::LAMP,
            ));
            let r = rng.range(0.16, 0.22);
            if rng.chance(0.5) {
                parts.push(cylinder(0.0, 0.0, (h - 0.25, h), r, shade, label::LAMP));
            } else {
                parts.push(sphere([0.0, 0.0, h - 0.17], 0.17, shade, label::LAMP));
            }
            (label::LAMP, 0.22, 0.22, h, floor(0.0, (0.1, 0.3)), None)
        }
        Kind::Crate => {
            let (sx, sy, sz) = (
                rng.range(0.15, 0.3),
                rng.range(0.15, 0.3),
                rng.range(0.12, 0.25),
            );
            let card = [0.62, 0.47, 0.3];
            let tape = Material::new(
                darker(card, 0.75),
                card,
                Pattern::Stripes {
                    period: rng.range(0.06, 0.12),
                    axis: 0,
                },
                rng,
            );
            parts.push(cuboid([0.0, 0.0, sz], [sx, sy, sz], tape, label::BOX));
            (label::BOX, sx, sy, 2.0 * sz, floor(0.8, (0.05, 0.4)), None)
        }
        Kind::Ball => {
            let r = rng.range(0.12, 0.25);
            parts.push(sphere([0.0, 0.0, r], r, poster(rng), label::OTHERPROP));
            (
                label::OTHERPROP,
                r,
                r,
                2.0 * r,
                floor(0.0, (0.1, 0.5)),
                None,
            )
        }
        Kind::Picture | Kind::Television | Kind::Whiteboard | Kind::Window => {
            let (label, w, h, bottom, t) = match kind {
                Kind::Picture => (
                    label::PICTURE,
                    rng.range(0.4, 1.0),
                    rng.range(0.3, 0.8),
                    rng.range(1.1, 1.4),
                    0.03,
                ),
                Kind::Television => {
                    let w = rng.range(0.8, 1.3);
                    (label::TELEVISION, w, 0.58 * w, rng.range(1.0, 1.2), 0.06)
                }
                Kind::Whiteboard => (
                    label::WHITEBOARD,
                    rng.range(1.0, 1.8),
                    rng.range(0.7, 1.0),
                    rng.range(1.0, 1.1),
                    0.025,
                ),
                _ => (
                    label::WINDOW,
                    rng.range(0.8, 1.4),
                    rng.range(0.9, 1.3),
                    rng.range(1.0, 1.1),
                    0.06,
                ),
            };
            let h = h.min(room_height - 0.15 - bottom);
            let zc = bottom + h / 2.0;
            match kind {
                Kind::Window => {
                    // A frame of bars, a cross, and sky behind, recessed.
                    let (frame, sky) = (paint(rng), {
                        let sky = [0.55, 0.72, 0.92];
                        Material::new(
                            sky,
                            [0.95, 0.96, 0.98],
                            Pattern::Blobs {
                                wavelength: rng.range(0.15, 0.3),
                            },
                            rng,
                        )
                    });
                    let b = 0.05;
                    parts.push(cuboid(
                        [0.0, -t / 4.0, zc],
                        [w / 2.0, t / 4.0, h / 2.0],
                        sky,
                        label,
                    ));
                    for sz in [-1.0, 1.0] {
                        parts.push(cuboid(
                            [0.0, 0.0, zc + sz * (h / 2.0 - b / 2.0)],
                            [w / 2.0, t / 2.0, b / 2.0],
                            frame,
                            label,
                        ));
                        parts.push(cuboid(
                            [sz * (w / 2.0 - b / 2.0), 0.0, zc],
                            [b / 2.0, t / 2.0, h / 2.0],
                            frame,
                            label,
                        ));
                    }
                    parts.push(cuboid(
                        [0.0, 0.0, zc],
                        [0.02, t / 2.0 - 0.01, h / 2.0],
                        frame,
                        label,
                    ));
                    parts.push(cuboid(
                        [0.0, 0.0, zc],
                        [w / 2.0, t / 2.0 - 0.01, 0.02],
                        frame,
                        label,
                    ));
                }
                Kind::Television => {
                    let body = Material::new(
                        [0.06; 3],
                        [0.16; 3],
                        Pattern::Plaster { wavelength: 0.2 },
                        rng,
                    );
                    parts.push(cuboid(
                        [0.0, 0.0, zc],
                        [w / 2.0, t / 2.0, h / 2.0],
                        body,
                        label,
                    ));
                    parts.push(cuboid(
                        [0.0, t / 2.0 + 0.004, zc],
                        [w / 2.0 - 0.03, 0.004, h / 2.0 - 0.03],
                        poster(rng),
                        label,
                    ));
                }
                Kind::Whiteboard => {
                    let ink = pick(rng, &palette::BRIGHT);
                    let board = Material::new(
                        [0.96, 0.96, 0.95],
                        ink,
                        Pattern::Blobs {
                            wavelength: rng.range(0.1, 0.2),
                        },
                        rng,
                    );
                    parts.push(cuboid(
                        [0.0, 0.0, zc],
                        [w / 2.0, t / 2.0, h / 2.0],
                        metal(rng),
                        label,
                    ));
                    parts.push(cuboid(
                        [0.0, t / 2.0 + 0.003, zc],
                        [w / 2.0 - 0.03, 0.003, h / 2.0 - 0.03],
                        board,
                        label,
                    ));
                }
                _ => {
                    parts.push(cuboid(
                        [0.0, 0.0, zc],
                        [w / 2.0, t / 2.0, h / 2.0],
                        wood(rng),
                        label,
                    ));
                    parts.push(cuboid(
                        [0.0, t / 2.0 + 0.004, zc],
                        [w / 2.0 - 0.04, 0.004, h / 2.0 - 0.04],
                        poster(rng),
                        label,
                    ));
                }
            }
            (label, w / 2.0, t / 2.0, bottom + h, Mount::Wall, None)
        }
        Kind::Pilaster => {
            let (w, d) = (rng.range(0.2, 0.4), rng.range(0.08, 0.16));
            parts.push(cuboid(
                [0.0, 0.0, room_height / 2.0],
                [w / 2.0, d / 2.0, room_height / 2.0],
                paint(rng),
                label::OTHERSTRUCTURE,
            ));
            (
                label::OTHERSTRUCTURE,
                w / 2.0,
                d / 2.0,
                room_height,
                floor(0.0, (0.0, 0.0)),
                None,
            )
        }
        Kind::Door => {
            let (w, t) = (rng.range(0.8, 0.95), 0.04);
            let h = rng.range(2.0, 2.1).min(room_height - 0.12);
            let (leaf, handle) = (wood(rng), metal(rng));
            parts.push(cuboid(
                [0.0, 0.0, h / 2.0],
                [w / 2.0, t / 2.0, h / 2.0],
                leaf,
                label::DOOR,
            ));
            parts.push(cylinder(
                w / 2.0 - 0.08,
                t / 2.0 + 0.03,
                (0.95, 1.12),
                0.015,
                handle,
                label::DOOR,
            ));
            (label::DOOR, w / 2.0, t / 2.0, h, Mount::Door, None)
        }
    };
    Design {
        label,
        hx,
        hy,
        height,
        mount,
        parts,
        top,
    }
}

/// A small prop for a flat top at height `z`: its parts (origin on the top), label and footprint
/// half size.
fn prop(rng: &mut Rng, z: f64) -> (Vec<(Shape, Material, u16)>, u16, f64) {
    match rng.below(3) {
        0 => {
            let r = rng.range(0.06, 0.12);
            (
                vec![sphere([0.0, 0.0, z + r], r, poster(rng), label::OTHERPROP)],
                label::OTHERPROP,
                r,
            )
        }
        1 => {
            let s = rng.range(0.06, 0.15);
            let hz = rng.range(0.05, 0.12);
            (
                vec![cuboid(
                    [0.0, 0.0, z + hz],
                    [s, 0.8 * s, hz],
                    poster(rng),
                    label::BOX,
                )],
                label::BOX,
                1.3 * s,
            )
        }
        _ => {
            let (base, shade) = (metal(rng), fabric(rng));
            let parts = vec![
                cylinder(0.0, 0.0, (z, z + 0.025), 0.07, base, label::LAMP),
                cylinder(0.0, 0.0, (z + 0.025, z + 0.28), 0.012, base, label::LAMP),
                sphere([0.0, 0.0, z + 0.36], 0.1, shade, label::LAMP),
            ];
            (parts, label::LAMP, 0.1)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn furniture_stays_inside_the_room_and_out_of_the_keepout_disk() {
        for seed in 0..20 {
            let size = [5.5, 4.5, 2.7];
            let layout = Layout::generate(seed, size, 14, 1.4);
            assert!(
                layout.objects.len() >= 6 + 10,
                "seed {seed}: {}",
                layout.objects.len()
            );
            for part in &layout.parts {
                let b = part.aabb;
                assert!(
                    b.min.x >= -2.75 - 1e-9 && b.max.x <= 2.75 + 1e-9,
                    "seed {seed}: {b:?}"
                );
                assert!(
                    b.min.y >= -2.25 - 1e-9 && b.max.y <= 2.25 + 1e-9,
                    "seed {seed}: {b:?}"
                );
                assert!(
                    b.min.z >= -1e-9 && b.max.z <= 2.7 - 0.05,
                    "seed {seed}: {b:?}"
                );
                // Nothing reaches into the keep-out disk (a box's bounds may, its footprint not).
                let closest = Vector3::new(
                    0.0_f64.clamp(b.min.x, b.max.x),
                    0.0_f64.clamp(b.min.y, b.max.y),
                    0.0,
                );
                assert!(closest.norm() > 1.0, "seed {seed}: {b:?}");
            }
            let spans: usize = layout.spans.iter().map(|s| s.parts.len()).sum();
            assert_eq!(spans, layout.parts.len());
            assert_eq!(layout.spans.len() + 6, layout.objects.len());
        }
    }

    #[test]
    fn retaining_pieces_renumbers_instances() {
        let mut layout = Layout::generate(3, [5.5, 4.5, 2.7], 14, 1.4);
        let before = layout.objects.clone();
        layout.retain_pieces(|instance| instance % 2 == 0);
        assert_eq!(layout.objects[..6], before[..6]);
        for (i, object) in layout.objects.iter().enumerate() {
            assert_eq!(usize::from(object.instance), i + 1);
        }
        let kept: Vec<_> = before[6..].iter().filter(|o| o.instance % 2 == 0).collect();
        assert_eq!(layout.objects.len(), 6 + kept.len());
        for (object, old) in layout.objects[6..].iter().zip(kept) {
            assert_eq!(
                (object.label, object.min, object.max),
                (old.label, old.min, old.max)
            );
        }
        assert_eq!(layout.spans.len() + 6, layout.objects.len());
        for (span, object) in layout.spans.iter().zip(&layout.objects[6..]) {
            assert!(
                layout.parts[span.parts.clone()]
                    .iter()
                    .all(|p| p.instance == object.instance)
            );
        }
    }

    #[test]
    fn every_core_class_is_placed_in_the_default_room() {
        let layout = Layout::generate(0, [5.5, 4.5, 2.7], 14, 1.4);
        let labels: Vec<u16> = layout.objects.iter().map(|o| o.label).collect();
        for l in [
            label::SOFA,
            label::TABLE,
            label::CHAIR,
            label::CABINET,
            label::LAMP,
        ] {
            assert!(labels.contains(&l), "{} missing: {labels:?}", label_name(l));
        }
    }
}
