//! A one-dimensional Gaussian mixture fitted by expectation–maximisation: the paper's similarity
//! clustering, which keeps only the points of the highest-similarity population.

use rayon::prelude::*;

/// Variance added to every component, as scikit-learn's `reg_covar`: keeps a component that
/// collapses onto identical scores from a zero variance (an infinite density).
const VARIANCE_FLOOR: f64 = 1e-6;
/// EM stops when the mean log-likelihood per point improves by less than this.
const TOLERANCE: f64 = 1e-7;
/// EM stops after this many iterations at the latest.
const MAX_ITERATIONS: usize = 200;
/// Values per parallel chunk of an EM step (fixed, so sums do not depend on the thread count).
const CHUNK: usize = 8192;

/// A fitted mixture: one entry per component, in the order of the initial means (ascending).
#[derive(Clone, Debug, PartialEq)]
pub struct Gmm1d {
    /// Component means.
    pub means: Vec<f64>,
    /// Component variances (floored, never zero).
    pub variances: Vec<f64>,
    /// Mixing weights, summing to 1.
    pub weights: Vec<f64>,
}

impl Gmm1d {
    /// Fits `components` Gaussians to `values` by EM, with the means initialised evenly from the
    /// minimum to the maximum value (both included) and equal weights.
    ///
    /// `None` when there is nothing to fit: no finite values, zero components, or fewer values
    /// than components.
    pub fn fit(values: &[f32], components: usize) -> Option<Self> {
        let x: Vec<f64> = values
            .iter()
            .filter(|v| v.is_finite())
            .map(|&v| f64::from(v))
            .collect();
        if components == 0 || x.len() < components {
            return None;
        }
        let (lo, hi) = x
            .iter()
            .fold((f64::INFINITY, f64::NEG_INFINITY), |(lo, hi), &v| {
                (lo.min(v), hi.max(v))
            });
        let k = components;
        let step = if k > 1 {
            (hi - lo) / (k - 1) as f64
        } else {
            0.0
        };
        let mean = x.iter().sum::<f64>() / x.len() as f64;
        let variance =
            x.iter().map(|v| (v - mean) * (v - mean)).sum::<f64>() / x.len() as f64 / k as f64;
        let mut gmm = Self {
            means: (0..k)
                .map(|j| if k > 1 { lo + step * j as f64 } else { mean })
                .collect(),
            // The spread per component if the data split evenly; floored for constant data.
            variances: vec![variance + VARIANCE_FLOOR; k],
            weights: vec![1.0 / k as f64; k],
        };
        let mut resp = vec![0.0; x.len() * k];
        let mut previous = f64::NEG_INFINITY;
        for _ in 0..MAX_ITERATIONS {
            let (log_likelihood, nk, weighted_sum) = gmm.expectation(&x, &mut resp);
            gmm.maximisation(&x, &resp, &nk, &weighted_sum);
            if (log_likelihood - previous).abs() < TOLERANCE {
                break;
            }
            previous = log_likelihood;
        }
        Some(gmm)
    }

    /// Per component, the log density's terms that do not depend on the value: `ln w − ½ ln(2πσ²)`
    /// and `σ²`.
    fn terms(&self) -> Vec<(f64, f64, f64)> {
        (0..self.means.len())
            .map(|j| {
                let var = self.variances[j];
                let constant = self.weights[j].max(f64::MIN_POSITIVE).ln()
                    - 0.5 * (2.0 * std::f64::consts::PI * var).ln();
                (constant, self.means[j], var)
            })
            .collect()
    }

    /// Fills `resp[i * k + j]` with the posterior of component `j` for value `i`; returns the
    /// mean log-likelihood and, per component, the posteriors' sum and their sum weighted by the
    /// values (what the maximisation needs). Fixed-size chunks in parallel, their sums added in
    /// chunk order: the result does not depend on the number of threads.
    fn expectation(&self, x: &[f64], resp: &mut [f64]) -> (f64, Vec<f64>, Vec<f64>) {
        let k = self.means.len();
        let terms = self.terms();
        let partials: Vec<(f64, Vec<f64>, Vec<f64>)> = x
            .par_chunks(CHUNK)
            .zip(resp.par_chunks_mut(CHUNK * k))
            .map(|(x, resp)| {
                let (mut total, mut nk, mut sum) = (0.0, vec![0.0; k], vec![0.0; k]);
                for (&v, row) in x.iter().zip(resp.chunks_exact_mut(k)) {
                    for (r, &(constant, mean, var)) in row.iter_mut().zip(&terms) {
                        let d = v - mean;
                        *r = constant - 0.5 * d * d / var;
                    }
                    // Log-sum-exp: far from every mean, the densities underflow to zero in linear
                    // space.
                    let max = row.iter().copied().fold(f64::NEG_INFINITY, f64::max);
                    let mut norm = 0.0;
                    for r in row.iter_mut() {
                        *r = (*r - max).exp();
                        norm += *r;
                    }
                    for (j, r) in row.iter_mut().enumerate() {
                        *r /= norm;
                        nk[j] += *r;
                        sum[j] += *r * v;
                    }
                    total += max + norm.ln();
                }
                (total, nk, sum)
            })
            .collect();
        let (mut total, mut nk, mut sum) = (0.0, vec![0.0; k], vec![0.0; k]);
        for (t, n, s) in partials {
            total += t;
            nk.iter_mut().zip(n).for_each(|(a, b)| *a += b);
            sum.iter_mut().zip(s).for_each(|(a, b)| *a += b);
        }
        (total / x.len() as f64, nk, sum)
    }

    fn maximisation(&mut self, x: &[f64], resp: &[f64], nk: &[f64], weighted_sum: &[f64]) {
        let k = self.means.len();
        let means: Vec<f64> = (0..k)
            .map(|j| {
                if nk[j] <= f64::EPSILON {
                    self.means[j]
                } else {
                    weighted_sum[j] / nk[j]
                }
            })
            .collect();
        let spread: Vec<f64> = x
            .par_chunks(CHUNK)
            .zip(resp.par_chunks(CHUNK * k))
            .map(|(x, resp)| {
                let mut out = vec![0.0; k];
                for (&v, row) in x.iter().zip(resp.chunks_exact(k)) {
                    for ((o, &r), &mean) in out.iter_mut().zip(row).zip(&means) {
                        *o += r * (v - mean) * (v - mean);
                    }
                }
                out
            })
            .collect::<Vec<_>>()
            .into_iter()
            .fold(vec![0.0; k], |mut acc, part| {
                acc.iter_mut().zip(part).for_each(|(a, b)| *a += b);
                acc
            });
        for j in 0..k {
            self.weights[j] = nk[j] / x.len() as f64;
            // A component that lost every point keeps its mean and variance (and weight ≈ 0)
            // instead of dividing by zero.
            if nk[j] <= f64::EPSILON {
                continue;
            }
            self.means[j] = means[j];
            self.variances[j] = spread[j] / nk[j] + VARIANCE_FLOOR;
        }
    }

    /// The most likely component of `v`.
    pub fn predict(&self, v: f64) -> usize {
        Self::most_likely(&self.terms(), v)
    }

    /// The most likely component of `v` given [`Gmm1d::terms`].
    fn most_likely(terms: &[(f64, f64, f64)], v: f64) -> usize {
        terms
            .iter()
            .enumerate()
            .map(|(j, &(constant, mean, var))| (j, constant - 0.5 * (v - mean) * (v - mean) / var))
            .fold((0, f64::NEG_INFINITY), |best, (j, l)| {
                if l > best.1 { (j, l) } else { best }
            })
            .0
    }
}

/// Indices of the values whose most likely component is the highest-mean component that wins any
/// value (the paper: "select the cluster with the highest mean value").
///
/// Degenerate inputs keep every value: fewer values than `components`, or all values equal (there
/// is only one population). Non-finite values are never kept; an empty input gives nothing.
pub fn top_component(values: &[f32], components: usize) -> Vec<usize> {
    let finite = || (0..values.len()).filter(|&i| values[i].is_finite());
    let (lo, hi) = finite().fold((f32::INFINITY, f32::NEG_INFINITY), |(lo, hi), i| {
        (lo.min(values[i]), hi.max(values[i]))
    });
    // Also true when no value is finite (lo = +inf, hi = -inf).
    if hi <= lo {
        return finite().collect();
    }
    let Some(gmm) = Gmm1d::fit(values, components) else {
        return finite().collect();
    };
    let terms = gmm.terms();
    let labels: Vec<(usize, usize)> = finite()
        .map(|i| (i, Gmm1d::most_likely(&terms, f64::from(values[i]))))
        .collect();
    let mut used = vec![false; gmm.means.len()];
    labels.iter().for_each(|&(_, j)| used[j] = true);
    let top = (0..gmm.means.len())
        .filter(|&j| used[j])
        .max_by(|&a, &b| gmm.means[a].total_cmp(&gmm.means[b]));
    labels
        .into_iter()
        .filter(|&(_, j)| Some(j) == top)
        .map(|(i, _)| i)
        .collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Deterministic jitter in `[-1, 1]`.
    fn jitter(i: usize) -> f32 {
        ((i * 7919 % 1000) as f32 / 500.0) - 1.0
    }

    #[test]
    fn three_separated_populations_select_the_top_one() {
        let mut values = Vec::new();
        for i in 0..200 {
            values.push(0.2 + 0.02 * jitter(i));
        }
        for i in 0..150 {
            values.push(0.5 + 0.02 * jitter(i + 3));
        }
        for i in 0..60 {
            values.push(0.85 + 0.02 * jitter(i + 5));
        }
        let gmm = Gmm1d::fit(&values, 3).unwrap();
        let mut means = gmm.means.clone();
        means.sort_by(f64::total_cmp);
        for (m, want) in means.iter().zip([0.2, 0.5, 0.85]) {
            assert!((m - want).abs() < 0.01, "{means:?}");
        }
        assert!((gmm.weights.iter().sum::<f64>() - 1.0).abs() < 1e-9);
        let top = top_component(&values, 3);
        assert_eq!(top, (350..410).collect::<Vec<_>>());
    }

    #[test]
    fn degenerate_inputs_do_not_panic() {
        assert!(top_component(&[], 3).is_empty());
        assert_eq!(top_component(&[0.4; 10], 3), (0..10).collect::<Vec<_>>());
        assert_eq!(top_component(&[0.1, 0.9], 3), vec![0, 1]);
        assert_eq!(top_component(&[f32::NAN, 0.5, 0.5], 3), vec![1, 2]);
        assert!(Gmm1d::fit(&[0.1, 0.2], 3).is_none());
        assert!(Gmm1d::fit(&[0.1, 0.2], 0).is_none());
        // Constant data fits without a zero variance.
        let gmm = Gmm1d::fit(&[0.3; 5], 3).unwrap();
        assert!(gmm.variances.iter().all(|&v| v > 0.0));
        assert!(gmm.means.iter().all(|m| m.is_finite()));
    }

    #[test]
    fn two_populations_with_three_components_keep_the_upper_one() {
        let values: Vec<f32> = (0..100)
            .map(|i| if i < 70 { 0.3 } else { 0.8 } + 0.01 * jitter(i))
            .collect();
        // A third component may split one population; the kept points still all come from the
        // upper one.
        let top = top_component(&values, 3);
        assert!(!top.is_empty() && top.iter().all(|&i| i >= 70), "{top:?}");
    }
}
