//! Plane geometry used by the map builder, the rules and the observation code.
//!
//! Owns: 2-D points, angle wrapping, frame transforms, polyline resampling, offsetting,
//! projection, point-in-polygon, a uniform grid index and the nearest-first cut of candidate
//! lists (`nearest_first`, which the observer and the leader search share). Must not: know
//! about vehicles, lanes or scenarios. All angles are radians, all lengths metres.

use std::f32::consts::PI;

/// A point or vector in metres.
pub type P2 = [f32; 2];

#[inline]
pub fn sub(a: P2, b: P2) -> P2 {
    [a[0] - b[0], a[1] - b[1]]
}

#[inline]
pub fn add(a: P2, b: P2) -> P2 {
    [a[0] + b[0], a[1] + b[1]]
}

#[inline]
pub fn scale(a: P2, k: f32) -> P2 {
    [a[0] * k, a[1] * k]
}

#[inline]
pub fn dot(a: P2, b: P2) -> f32 {
    a[0] * b[0] + a[1] * b[1]
}

#[inline]
pub fn cross(a: P2, b: P2) -> f32 {
    a[0] * b[1] - a[1] * b[0]
}

#[inline]
pub fn norm(a: P2) -> f32 {
    (a[0] * a[0] + a[1] * a[1]).sqrt()
}

#[inline]
pub fn dist2(a: P2, b: P2) -> f32 {
    let d = sub(a, b);
    d[0] * d[0] + d[1] * d[1]
}

#[inline]
pub fn dist(a: P2, b: P2) -> f32 {
    dist2(a, b).sqrt()
}

/// Wraps an angle to (-pi, pi].
#[inline]
pub fn wrap_angle(a: f32) -> f32 {
    let mut x = a % (2.0 * PI);
    if x > PI {
        x -= 2.0 * PI
    } else if x <= -PI {
        x += 2.0 * PI
    }
    x
}

/// Unit vector of heading `theta_rad`.
#[inline]
pub fn heading_vec(theta_rad: f32) -> P2 {
    [theta_rad.cos(), theta_rad.sin()]
}

/// A rigid frame (origin + heading) with cached trigonometry, for world <-> local transforms.
#[derive(Clone, Copy, Debug)]
pub struct Frame {
    pub origin: P2,
    pub theta_rad: f32,
    cos: f32,
    sin: f32,
}

impl Frame {
    pub fn new(origin: P2, theta_rad: f32) -> Self {
        Self { origin, theta_rad, cos: theta_rad.cos(), sin: theta_rad.sin() }
    }

    /// World point -> this frame's coordinates.
    #[inline]
    pub fn to_local(&self, p: P2) -> P2 {
        let d = sub(p, self.origin);
        [d[0] * self.cos + d[1] * self.sin, -d[0] * self.sin + d[1] * self.cos]
    }

    /// This frame's coordinates -> world point.
    #[inline]
    pub fn to_world(&self, p: P2) -> P2 {
        [
            self.origin[0] + p[0] * self.cos - p[1] * self.sin,
            self.origin[1] + p[0] * self.sin + p[1] * self.cos,
        ]
    }

    /// World heading -> heading relative to this frame, wrapped.
    #[inline]
    pub fn angle_to_local(&self, theta_rad: f32) -> f32 {
        wrap_angle(theta_rad - self.theta_rad)
    }
}

/// Headings of a polyline's points: the direction of the outgoing segment (the last point
/// takes its incoming segment's direction).
pub fn polyline_headings(points: &[P2]) -> Vec<f32> {
    let n = points.len();
    (0..n)
        .map(|i| {
            let (a, b) =
                if i + 1 < n { (points[i], points[i + 1]) } else { (points[i - 1], points[i]) };
            let d = sub(b, a);
            d[1].atan2(d[0])
        })
        .collect()
}

/// Cumulative arc length at each point.
pub fn cumulative_lengths(points: &[P2]) -> Vec<f32> {
    let mut out = Vec::with_capacity(points.len());
    let mut s = 0.0;
    for i in 0..points.len() {
        if i > 0 {
            s += dist(points[i - 1], points[i]);
        }
        out.push(s);
    }
    out
}

/// Point and heading at arc length `s_m` along a polyline (clamped to its ends).
pub fn point_at(points: &[P2], cum: &[f32], s_m: f32) -> (P2, f32) {
    let n = points.len();
    let s = s_m.clamp(0.0, cum[n - 1]);
    let i = match cum.binary_search_by(|c| c.total_cmp(&s)) {
        Ok(i) => i.min(n - 2),
        Err(i) => i.saturating_sub(1).min(n - 2),
    };
    let seg = cum[i + 1] - cum[i];
    let t = if seg > 0.0 { (s - cum[i]) / seg } else { 0.0 };
    let d = sub(points[i + 1], points[i]);
    (add(points[i], scale(d, t)), d[1].atan2(d[0]))
}

/// Resamples a polyline at a fixed spacing; keeps both end points exactly.
pub fn resample(points: &[P2], spacing_m: f32) -> Vec<P2> {
    let cum = cumulative_lengths(points);
    let total = cum[cum.len() - 1];
    let n = ((total / spacing_m).round() as usize).max(1);
    (0..=n).map(|k| point_at(points, &cum, total * k as f32 / n as f32).0).collect()
}

/// Offsets a polyline sideways; positive `offset_m` is to the left of travel.
pub fn offset_polyline(points: &[P2], offset_m: f32) -> Vec<P2> {
    let n = points.len();
    (0..n)
        .map(|i| {
            let prev = if i > 0 { points[i - 1] } else { points[i] };
            let next = if i + 1 < n { points[i + 1] } else { points[i] };
            let d = sub(next, prev);
            let l = norm(d).max(1e-9);
            let left = [-d[1] / l, d[0] / l];
            add(points[i], scale(left, offset_m))
        })
        .collect()
}

/// Result of projecting a point onto a polyline.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Projection {
    /// Index of the segment's first point.
    pub seg: usize,
    /// Arc length of the foot point.
    pub s_m: f32,
    /// Signed lateral offset, positive to the left of travel.
    pub lateral_m: f32,
}

/// Projects `p` onto segments `lo..hi` of a polyline (segment i joins point i and i + 1).
pub fn project_range(points: &[P2], cum: &[f32], p: P2, lo: usize, hi: usize) -> Projection {
    let hi = hi.min(points.len() - 1);
    let mut best = Projection { seg: lo, s_m: cum[lo], lateral_m: f32::INFINITY };
    let mut best_d2 = f32::INFINITY;
    for i in lo..hi {
        let a = points[i];
        let d = sub(points[i + 1], a);
        let l2 = dot(d, d).max(1e-12);
        let t = (dot(sub(p, a), d) / l2).clamp(0.0, 1.0);
        let foot = add(a, scale(d, t));
        let d2 = dist2(p, foot);
        if d2 < best_d2 {
            best_d2 = d2;
            let side = cross(d, sub(p, a)).signum();
            best = Projection { seg: i, s_m: cum[i] + t * l2.sqrt(), lateral_m: side * d2.sqrt() };
        }
    }
    best
}

/// Even-odd point-in-polygon test (the polygon is implicitly closed).
pub fn point_in_polygon(p: P2, poly: &[P2]) -> bool {
    let mut inside = false;
    let n = poly.len();
    let mut j = n - 1;
    for i in 0..n {
        let (a, b) = (poly[i], poly[j]);
        if (a[1] > p[1]) != (b[1] > p[1]) {
            let x = a[0] + (p[1] - a[1]) * (b[0] - a[0]) / (b[1] - a[1]);
            if p[0] < x {
                inside = !inside;
            }
        }
        j = i;
    }
    inside
}

/// Whether two segments intersect (touching counts).
pub fn segments_intersect(a0: P2, a1: P2, b0: P2, b1: P2) -> bool {
    let d1 = cross(sub(a1, a0), sub(b0, a0));
    let d2 = cross(sub(a1, a0), sub(b1, a0));
    let d3 = cross(sub(b1, b0), sub(a0, b0));
    let d4 = cross(sub(b1, b0), sub(a1, b0));
    (d1 * d2 <= 0.0) && (d3 * d4 <= 0.0)
}

/// A uniform grid over a rectangle that maps cells to item indices, for neighbourhood queries.
#[derive(Clone, Debug)]
pub struct Grid {
    min: P2,
    cell_m: f32,
    nx: usize,
    ny: usize,
    /// CSR layout: items of cell c are `items[starts[c]..starts[c + 1]]`.
    starts: Vec<u32>,
    items: Vec<u32>,
}

impl Grid {
    /// Builds a grid; `boxes[i]` is item i's axis-aligned bounding box (min, max).
    pub fn build(min: P2, max: P2, cell_m: f32, boxes: &[(P2, P2)]) -> Self {
        let nx = (((max[0] - min[0]) / cell_m).ceil() as usize).max(1);
        let ny = (((max[1] - min[1]) / cell_m).ceil() as usize).max(1);
        let mut cells: Vec<Vec<u32>> = vec![Vec::new(); nx * ny];
        let mut g = Self { min, cell_m, nx, ny, starts: Vec::new(), items: Vec::new() };
        for (i, (lo, hi)) in boxes.iter().enumerate() {
            let (x0, y0) = g.cell_of(*lo);
            let (x1, y1) = g.cell_of(*hi);
            for cy in y0..=y1 {
                for cx in x0..=x1 {
                    cells[cy * nx + cx].push(i as u32);
                }
            }
        }
        g.starts.push(0);
        for c in &cells {
            g.items.extend_from_slice(c);
            g.starts.push(g.items.len() as u32);
        }
        g
    }

    #[inline]
    fn cell_of(&self, p: P2) -> (usize, usize) {
        let cx =
            ((p[0] - self.min[0]) / self.cell_m).floor().clamp(0.0, (self.nx - 1) as f32) as usize;
        let cy =
            ((p[1] - self.min[1]) / self.cell_m).floor().clamp(0.0, (self.ny - 1) as f32) as usize;
        (cx, cy)
    }

    /// Calls `f` with each item whose cells overlap the box around `p` of half-size `r`.
    /// An item spanning several cells may be reported more than once.
    #[inline]
    pub fn for_each_near(&self, p: P2, r: f32, mut f: impl FnMut(usize)) {
        let (x0, y0) = self.cell_of([p[0] - r, p[1] - r]);
        let (x1, y1) = self.cell_of([p[0] + r, p[1] + r]);
        for cy in y0..=y1 {
            for cx in x0..=x1 {
                let c = cy * self.nx + cx;
                for &it in &self.items[self.starts[c] as usize..self.starts[c + 1] as usize] {
                    f(it as usize);
                }
            }
        }
    }
}

/// Keeps the `cap` smallest (distance, index) pairs, sorted ascending.
pub(crate) fn nearest_first(v: &mut Vec<(f32, u32)>, cap: usize) {
    let cmp = |a: &(f32, u32), b: &(f32, u32)| a.0.total_cmp(&b.0).then(a.1.cmp(&b.1));
    if v.len() > cap {
        if cap > 0 {
            v.select_nth_unstable_by(cap - 1, cmp);
        }
        v.truncate(cap);
    }
    v.sort_unstable_by(cmp);
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn frame_round_trip_and_axes() {
        let f = Frame::new([3.0, -2.0], 0.7);
        let p = [10.0, 5.0];
        let q = f.to_world(f.to_local(p));
        assert!(dist(p, q) < 1e-4);
        // The frame's own heading maps onto +x.
        let ahead = add(f.origin, heading_vec(0.7));
        let l = f.to_local(ahead);
        assert!((l[0] - 1.0).abs() < 1e-5 && l[1].abs() < 1e-5);
    }

    #[test]
    fn wrap_angle_range() {
        for k in -20..20 {
            let a = wrap_angle(k as f32 * 0.9);
            assert!(a > -PI - 1e-6 && a <= PI + 1e-6);
        }
        assert!((wrap_angle(3.0 * PI) - PI).abs() < 1e-5);
    }

    #[test]
    fn projection_signs_and_arc_length() {
        let pts = vec![[0.0, 0.0], [10.0, 0.0], [20.0, 0.0]];
        let cum = cumulative_lengths(&pts);
        let pr = project_range(&pts, &cum, [12.0, 3.0], 0, 2);
        assert_eq!(pr.seg, 1);
        assert!((pr.s_m - 12.0).abs() < 1e-5);
        assert!((pr.lateral_m - 3.0).abs() < 1e-5);
        let pr = project_range(&pts, &cum, [5.0, -2.0], 0, 2);
        assert!((pr.lateral_m + 2.0).abs() < 1e-5);
    }

    #[test]
    fn polygon_and_segments() {
        let sq = [[0.0, 0.0], [1.0, 0.0], [1.0, 1.0], [0.0, 1.0]];
        assert!(point_in_polygon([0.5, 0.5], &sq));
        assert!(!point_in_polygon([1.5, 0.5], &sq));
        assert!(segments_intersect([0.0, 0.0], [1.0, 1.0], [0.0, 1.0], [1.0, 0.0]));
        assert!(!segments_intersect([0.0, 0.0], [1.0, 0.0], [0.0, 1.0], [1.0, 1.0]));
    }

    #[test]
    fn resample_keeps_ends_and_spacing() {
        let pts = vec![[0.0, 0.0], [9.0, 0.0]];
        let r = resample(&pts, 2.0);
        assert_eq!(r.first(), Some(&[0.0, 0.0]));
        assert!(dist(*r.last().expect("non-empty"), [9.0, 0.0]) < 1e-5);
        for w in r.windows(2) {
            assert!((dist(w[0], w[1]) - 1.8).abs() < 1e-4);
        }
    }
}
