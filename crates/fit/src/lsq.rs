//! The one nonlinear least-squares path of the crate: one loop ([`run`]) that minimizes a
//! chi^2 over parameters from a problem's evaluations and linearizations ([`Problem`]), under
//! a small named [`Policy`] that states the step and its damping, the stopping rule and the
//! iteration limit; a [`Ladder`] of runs for the Gauss-Newton policies; one failure contract
//! ([`LsqError`], and the [`Ending`] of every run).
//!
//! # The four fits and how their loops differed
//!
//! The radial model ([`crate::models::radial`]), the telescope model ([`crate::telescope`]), the
//! Mueller field ([`crate::mueller_field`]) and the candidate causes
//! ([`crate::mueller_field::explain`]) each had their own loop. What they share: a step from the
//! normal equations `A delta = v` (`A = J^T W J`, `v = -J^T W r`), a chi^2 that decides whether
//! a point is kept, a stopping rule on the change of that chi^2, an iteration limit; and the
//! caller computes the covariance from the linearization at the end. How they differed, which
//! the policies below keep exactly (every fit gives the same bits as before,
//! `tests/it/lsq_bits.rs` and the numbers of record):
//!
//! - problem: the radial fit's residuals with their analytic Jacobian; the telescope's and
//!   the causes' with central-difference Jacobians; the Mueller field's normal equations and
//!   chi^2 directly.
//! - step: radial and telescope `x - g (J^T J)^-1 J^T r` with the inverse formed; the Mueller
//!   field the Cholesky solution of the damped normal equations; the causes their LU
//!   solution.
//! - damping: radial whole runs with `g = 1, 1/2, 1/4`; telescope `g = 1, 1/2, 1/5`; the
//!   Mueller field `A_ii (1 + lambda)`, lambda from 1e-6, up x10, down x0.1 to 1e-12; the
//!   causes `A_ii + lambda max(A_ii, 1e-12)`, lambda from 1e-3, up x10, down x0.2 to 1e-12.
//! - acceptance: radial and telescope take every step and keep a run's best point, radial if
//!   its chi^2 is finite and at most the start's times `1 + 1e-12`, telescope if finite and
//!   below the best so far; the Mueller field a trial whose chi^2 is not above (10 tries),
//!   the causes one whose chi^2 is below (12 tries).
//! - stopping: radial and telescope `abs(|r_old| - |r_new|) < 2^-26`; the Mueller field a
//!   decrease below `1e-10 max(chi^2, 1)`; the causes below `1e-9 max(chi^2, 1e-30) + 1e-12`.
//! - iterations: radial 50, 200, 200 per run; telescope 100 per run; the Mueller field the
//!   options' `max_iter` (30); the causes 60.
//! - runs: radial until the first run kept, each from the start; telescope all three, each
//!   from the best so far; the Mueller field one; the causes one per start.
//! - failure: radial, no run kept, an error naming the last run's reason; telescope, no run
//!   kept, the start; the Mueller field and the causes none (the last point; the causes refuse
//!   a start whose chi^2 is not finite themselves).
//!
//! The two Gauss-Newton ladders were argmin's `GaussNewton` solver (its `gamma` is the step
//! fraction; its stopping rule compares the residual norms `|r| = sqrt(chi^2)` with
//! `sqrt(f64::EPSILON)`, and a run's result is the best point by that norm); [`run`] reproduces
//! it step for step (the test `gauss_newton_runs_are_argmins` checks the bits against argmin).
//! The Levenberg-Marquardt loops scale the damping differently (Marquardt's multiplicative
//! form against an additive one with a floor, for the causes' parameters of very different
//! sizes) and were tuned separately; one ladder for all would move every fit by its stopping
//! tolerance, far above the 1e-12 of the numbers of record, so the policies stay four.
//!
//! # The loop
//!
//! At the top of each iteration the problem is linearized at the current point (a failure ends
//! the run: [`Ending::Failed`]). A Gauss-Newton step is always taken (a weighted design matrix
//! the conditioning judge refuses, [`crate::conditioning::judge`], a singular normal matrix or
//! a point that cannot be evaluated ends the run as failed) and the run's result is the best
//! point visited. A Levenberg-Marquardt iteration tries damped steps up the lambda ladder until
//! one is accepted (a damped matrix that cannot be factorized or a trial point that cannot be
//! evaluated counts as a rejected step); none accepted ends the run ([`Ending::NoDecrease`]).
//! After an accepted step the stopping rule may end the run ([`Ending::Converged`]); otherwise
//! the iteration limit does ([`Ending::IterationLimit`]).

use nalgebra::{DMatrix, DVector};

/// Why a least-squares run or ladder failed.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum LsqError {
    /// The normal matrix of an undamped step could not be inverted.
    #[error("the normal matrix is singular")]
    Singular,
    /// No run of a ladder reached a chi^2 its rule keeps (`to`: the last run's, `from`: the
    /// one it had to beat).
    #[error("chi^2 rose from {from} to {to}")]
    NoDecrease { from: f64, to: f64 },
    /// The problem could not be evaluated or linearized at a point (its own words).
    #[error("{0}")]
    Evaluation(String),
    /// The data do not determine a parameter at a point ([`crate::conditioning::judge`] on the
    /// weighted design matrix of a Gauss-Newton step).
    #[error(transparent)]
    Undetermined(#[from] crate::conditioning::Undetermined),
}

/// What the loop needs of a problem: the model at a point and its linearization there.
pub trait Problem {
    /// One evaluation at a point (the residuals, or only the chi^2).
    type Eval: Clone;
    /// What the linearization leaves for the caller (the Jacobian, for a covariance).
    type Lin;
    /// The model at `x`; an error when `x` is outside the problem's domain.
    fn evaluate(&self, x: &[f64]) -> Result<Self::Eval, LsqError>;
    /// The chi^2 of an evaluation: what the acceptance and stopping rules compare.
    fn chi2(&self, e: &Self::Eval) -> f64;
    /// The normal equations at `x` (evaluated as `e`).
    fn linearize(&self, x: &[f64], e: &Self::Eval) -> Result<Linear<Self::Lin>, LsqError>;
    /// The conditioning judge's words for the parameters (their names, and the input that
    /// determines them); by default their numbers.
    fn words(&self, n: usize) -> crate::conditioning::Words {
        crate::conditioning::Words::new(
            (1..=n).map(|k| format!("parameter {k}")).collect(),
            "more data, or data that vary in what this fit models",
        )
    }
}

/// The normal equations at a point: the Gauss-Newton step `delta` solves `normal delta = rhs`.
#[derive(Debug, Clone)]
pub struct Linear<L> {
    /// `J^T W J`.
    pub normal: DMatrix<f64>,
    /// `-J^T W r` (minus half the gradient of chi^2).
    pub rhs: DVector<f64>,
    /// What the caller gets back with the solution.
    pub kept: L,
    /// The weighted design matrix `W^1/2 J`, when the problem has one: what a Gauss-Newton step
    /// has judged ([`crate::conditioning::judge`]) before it inverts.
    pub design: Option<DMatrix<f64>>,
}

impl Linear<DMatrix<f64>> {
    /// The normal equations of standardized residuals `r` with Jacobian `j` (chi^2 = `|r|^2`),
    /// keeping `j`.
    pub fn of_jacobian(j: DMatrix<f64>, r: &DVector<f64>) -> Self {
        let normal = j.transpose() * &j;
        let rhs = -(j.transpose() * r);
        Linear { normal, rhs, design: Some(j.clone()), kept: j }
    }
}

/// How a step is made.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Step {
    /// Gauss-Newton: `x + fraction (J^T J)^-1 (-J^T r)` with the inverse formed, every step
    /// taken; the run's result is the best point visited, by the residual norm
    /// `sqrt(chi^2)` (argmin's `GaussNewton` with `gamma = fraction`).
    GaussNewton { fraction: f64 },
    /// Levenberg-Marquardt: the damped normal equations solved, the trial accepted by a rule.
    Marquardt(Marquardt),
}

/// A Levenberg-Marquardt ladder.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Marquardt {
    /// The damping at the start of a run.
    pub lambda: f64,
    /// Factor on lambda after a rejected trial (or a damped matrix that could not be solved).
    pub up: f64,
    /// Factor on lambda after an accepted trial, and its floor.
    pub down: f64,
    pub floor: f64,
    /// Trials per iteration before the run ends with no decrease.
    pub tries: usize,
    pub diagonal: Diagonal,
    pub solve: Solve,
    pub accept: Accept,
}

/// How lambda damps the normal matrix's diagonal.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Diagonal {
    /// `A_ii (1 + lambda)` (Marquardt 1963).
    Scale,
    /// `A_ii + lambda max(A_ii, min)`: a parameter with no information still gets a damping.
    Add { min: f64 },
}

/// How the damped normal equations are solved (a failure is a rejected trial).
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Solve {
    Cholesky,
    Lu,
}

/// When a new chi^2 is kept against an old one.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Accept {
    /// `new <= old (1 + rel)`.
    NotWorse { rel: f64 },
    /// `new < old`.
    Lower,
}

impl Accept {
    fn accepts(self, new: f64, old: f64) -> bool {
        match self {
            Accept::NotWorse { rel } => new <= old * (1.0 + rel),
            Accept::Lower => new < old,
        }
    }
}

/// When a step ends the run as converged.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Stop {
    /// `abs(sqrt(chi2_old) - sqrt(chi2_new)) < tol`: the change of the residual norm
    /// (argmin's Gauss-Newton rule).
    NormChange { tol: f64 },
    /// `chi2_old - chi2_new < rel max(chi2_old, floor) + abs`.
    Decrease { rel: f64, floor: f64, abs: f64 },
}

impl Stop {
    fn reached(self, old: f64, new: f64) -> bool {
        match self {
            Stop::NormChange { tol } => (old.sqrt() - new.sqrt()).abs() < tol,
            Stop::Decrease { rel, floor, abs } => old - new < rel * old.max(floor) + abs,
        }
    }
}

/// One run's rules.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Policy {
    pub step: Step,
    pub stop: Stop,
    pub max_iter: usize,
}

/// Runs in turn, each from the best point kept so far (the start until one is kept); a run
/// that failed is dropped, one that did not end at a finite chi^2 that `keep` accepts against
/// the point it started from is not kept.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Ladder {
    pub rungs: &'static [Policy],
    pub keep: Accept,
    /// End at the first run kept (else run every rung).
    pub until_kept: bool,
}

/// argmin's Gauss-Newton tolerance `sqrt(f64::EPSILON)`, which is `2^-26` exactly.
pub const ARGMIN_TOL: f64 = 1.0 / (1u64 << 26) as f64;

const fn gauss_newton(fraction: f64, max_iter: usize) -> Policy {
    Policy { step: Step::GaussNewton { fraction }, stop: Stop::NormChange { tol: ARGMIN_TOL }, max_iter }
}

/// The radial fit's: full steps, then half and quarter steps (a free centre far from the
/// start overshoots), each run from the start; the first run not worse than the start wins.
pub const RADIAL: Ladder = Ladder {
    rungs: &[gauss_newton(1.0, 50), gauss_newton(0.5, 200), gauss_newton(0.25, 200)],
    keep: Accept::NotWorse { rel: 1e-12 },
    until_kept: true,
};

/// The telescope fit's: full, half and fifth steps, each run from the best point so far, all
/// three run (a shorter step may still improve on a converged full-step run).
pub const TELESCOPE: Ladder = Ladder {
    rungs: &[gauss_newton(1.0, 100), gauss_newton(0.5, 100), gauss_newton(0.2, 100)],
    keep: Accept::Lower,
    until_kept: false,
};

/// The Mueller field's (`max_iter` is the fit options' own).
pub const MUELLER_FIELD: Policy = Policy {
    step: Step::Marquardt(Marquardt {
        lambda: 1e-6,
        up: 10.0,
        down: 0.1,
        floor: 1e-12,
        tries: 10,
        diagonal: Diagonal::Scale,
        solve: Solve::Cholesky,
        accept: Accept::NotWorse { rel: 0.0 },
    }),
    stop: Stop::Decrease { rel: 1e-10, floor: 1.0, abs: 0.0 },
    max_iter: 30,
};

/// The candidate causes'.
pub const CAUSES: Policy = Policy {
    step: Step::Marquardt(Marquardt {
        lambda: 1e-3,
        up: 10.0,
        down: 0.2,
        floor: 1e-12,
        tries: 12,
        diagonal: Diagonal::Add { min: 1e-12 },
        solve: Solve::Lu,
        accept: Accept::Lower,
    }),
    stop: Stop::Decrease { rel: 1e-9, floor: 1e-30, abs: 1e-12 },
    max_iter: 60,
};

/// Why a run ended.
#[derive(Debug, Clone, PartialEq)]
pub enum Ending {
    /// The stopping rule held after a step.
    Converged,
    /// No damped trial of an iteration was accepted.
    NoDecrease,
    /// `max_iter` iterations were made.
    IterationLimit,
    /// The run could not go on (singular normal matrix, a point not evaluated).
    Failed(LsqError),
}

/// Where a run ended.
#[derive(Debug, Clone)]
pub struct Solution<E, L> {
    /// The point: the last accepted one, or for Gauss-Newton the best visited.
    pub x: Vec<f64>,
    pub eval: E,
    pub chi2: f64,
    /// The last linearization made: of a Levenberg-Marquardt run at `x`, or at the point
    /// before its last step when the stopping rule or the iteration limit ended it; of a
    /// Gauss-Newton run at the point before its last step, which need not be `x`. `None` when
    /// the run made none.
    pub lin: Option<L>,
    pub ending: Ending,
}

/// One run from `x0` (evaluated as `e0`) under `policy`.
pub fn run<P: Problem>(problem: &P, x0: Vec<f64>, e0: P::Eval, policy: &Policy) -> Solution<P::Eval, P::Lin> {
    let (mut x, mut e) = (x0, e0);
    let mut chi2 = problem.chi2(&e);
    // Gauss-Newton's best point by the residual norm, kept as argmin's state does: strictly
    // lower replaces, and an infinite norm replaces an infinite best.
    let mut best: Option<(Vec<f64>, P::Eval, f64)> = None;
    let mut best_norm = f64::INFINITY;
    let mut consider = |x: &[f64], e: &P::Eval, chi2: f64, best: &mut Option<(Vec<f64>, P::Eval, f64)>| {
        let norm = chi2.sqrt();
        if norm < best_norm
            || (norm.is_infinite()
                && best_norm.is_infinite()
                && norm.is_sign_positive() == best_norm.is_sign_positive())
        {
            *best = Some((x.to_vec(), e.clone(), chi2));
            best_norm = norm;
        }
    };
    let keeps_best = matches!(policy.step, Step::GaussNewton { .. });
    if keeps_best {
        consider(&x, &e, chi2, &mut best);
    }
    let mut lambda = match policy.step {
        Step::Marquardt(m) => m.lambda,
        Step::GaussNewton { .. } => 0.0,
    };
    let mut lin = None;
    let mut ending = Ending::IterationLimit;
    for _ in 0..policy.max_iter {
        let l = match problem.linearize(&x, &e) {
            Ok(l) => l,
            Err(why) => {
                ending = Ending::Failed(why);
                break;
            }
        };
        let (normal, rhs) = (l.normal, l.rhs);
        lin = Some(l.kept);
        match policy.step {
            Step::GaussNewton { fraction } => {
                if let Some(Err(why)) = l.design.map(|d| crate::conditioning::judge(&d, &problem.words(x.len()))) {
                    ending = Ending::Failed(why.into());
                    break;
                }
                let Some(inv) = normal.try_inverse() else {
                    ending = Ending::Failed(LsqError::Singular);
                    break;
                };
                // argmin's order: p = (J^T J)^-1 (J^T r), x - p fraction.
                let p = &inv * &(-&rhs);
                let trial: Vec<f64> = x.iter().zip(p.iter()).map(|(a, s)| a - s * fraction).collect();
                let et = match problem.evaluate(&trial) {
                    Ok(et) => et,
                    Err(why) => {
                        ending = Ending::Failed(why);
                        break;
                    }
                };
                let ct = problem.chi2(&et);
                let stop = policy.stop.reached(chi2, ct);
                (x, e, chi2) = (trial, et, ct);
                consider(&x, &e, chi2, &mut best);
                if stop {
                    ending = Ending::Converged;
                    break;
                }
            }
            Step::Marquardt(m) => {
                let mut accepted = None;
                for _ in 0..m.tries {
                    let mut damped = normal.clone();
                    for i in 0..damped.nrows() {
                        match m.diagonal {
                            Diagonal::Scale => damped[(i, i)] *= 1.0 + lambda,
                            Diagonal::Add { min } => damped[(i, i)] += lambda * normal[(i, i)].max(min),
                        }
                    }
                    let step = match m.solve {
                        Solve::Cholesky => damped.cholesky().map(|c| c.solve(&rhs)),
                        Solve::Lu => damped.lu().solve(&rhs),
                    };
                    let Some(step) = step else {
                        lambda *= m.up;
                        continue;
                    };
                    let trial: Vec<f64> = x.iter().zip(step.iter()).map(|(a, s)| a + s).collect();
                    if let Ok(et) = problem.evaluate(&trial) {
                        let ct = problem.chi2(&et);
                        if m.accept.accepts(ct, chi2) {
                            accepted = Some(policy.stop.reached(chi2, ct));
                            (x, e, chi2) = (trial, et, ct);
                            lambda = (lambda * m.down).max(m.floor);
                            break;
                        }
                    }
                    lambda *= m.up;
                }
                match accepted {
                    None => {
                        ending = Ending::NoDecrease;
                        break;
                    }
                    Some(true) => {
                        ending = Ending::Converged;
                        break;
                    }
                    Some(false) => {}
                }
            }
        }
    }
    if let Some((bx, be, bc)) = best {
        (x, e, chi2) = (bx, be, bc);
    }
    Solution { x, eval: e, chi2, lin, ending }
}

/// The runs of `ladder` from `x0`: the last run kept, or why none was (the last run's failure,
/// or [`LsqError::NoDecrease`]); an error too when `x0` cannot be evaluated.
pub fn ladder<P: Problem>(problem: &P, x0: Vec<f64>, ladder: &Ladder) -> Result<Solution<P::Eval, P::Lin>, LsqError> {
    let e0 = problem.evaluate(&x0)?;
    let c0 = problem.chi2(&e0);
    let mut kept: Option<Solution<P::Eval, P::Lin>> = None;
    let mut why = LsqError::NoDecrease { from: c0, to: c0 };
    for rung in ladder.rungs {
        let (x, e, from) = match &kept {
            Some(s) => (s.x.clone(), s.eval.clone(), s.chi2),
            None => (x0.clone(), e0.clone(), c0),
        };
        let s = run(problem, x, e, rung);
        if let Ending::Failed(w) = s.ending {
            why = w;
            continue;
        }
        if s.chi2.is_finite() && ladder.keep.accepts(s.chi2, from) {
            kept = Some(s);
            if ladder.until_kept {
                break;
            }
        } else {
            why = LsqError::NoDecrease { from, to: s.chi2 };
        }
    }
    kept.ok_or(why)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Residuals `r(x)` and their Jacobian, written out; `domain` refuses points beyond it.
    #[derive(Clone, Copy)]
    struct Written {
        r: fn(&[f64]) -> Vec<f64>,
        j: fn(&[f64]) -> Vec<Vec<f64>>,
        domain: fn(&[f64]) -> bool,
    }

    impl Written {
        fn residuals(&self, x: &[f64]) -> DVector<f64> {
            DVector::from_vec((self.r)(x))
        }
        fn jacobian(&self, x: &[f64]) -> DMatrix<f64> {
            let rows = (self.j)(x);
            DMatrix::from_fn(rows.len(), x.len(), |i, k| rows[i][k])
        }
    }

    impl Problem for Written {
        type Eval = DVector<f64>;
        type Lin = DMatrix<f64>;
        fn evaluate(&self, x: &[f64]) -> Result<DVector<f64>, LsqError> {
            if (self.domain)(x) {
                Ok(self.residuals(x))
            } else {
                Err(LsqError::Evaluation(format!("{x:?} is outside the domain")))
            }
        }
        fn chi2(&self, r: &DVector<f64>) -> f64 {
            r.norm_squared()
        }
        fn linearize(&self, x: &[f64], r: &DVector<f64>) -> Result<Linear<DMatrix<f64>>, LsqError> {
            Ok(Linear::of_jacobian(self.jacobian(x), r))
        }
    }

    impl argmin::core::Operator for Written {
        type Param = DVector<f64>;
        type Output = DVector<f64>;
        fn apply(&self, p: &DVector<f64>) -> Result<DVector<f64>, argmin::core::Error> {
            Ok(self.residuals(p.as_slice()))
        }
    }

    impl argmin::core::Jacobian for Written {
        type Param = DVector<f64>;
        type Jacobian = DMatrix<f64>;
        fn jacobian(&self, p: &DVector<f64>) -> Result<DMatrix<f64>, argmin::core::Error> {
            Ok(Written::jacobian(self, p.as_slice()))
        }
    }

    fn anywhere(_: &[f64]) -> bool {
        true
    }

    /// Rosenbrock's function as residuals `(10 (y - x^2), 1 - x)`: minimum 0 at (1, 1).
    fn rosenbrock() -> Written {
        Written {
            r: |x| vec![10.0 * (x[1] - x[0] * x[0]), 1.0 - x[0]],
            j: |x| vec![vec![-20.0 * x[0], 10.0], vec![-1.0, 0.0]],
            domain: anywhere,
        }
    }

    /// `y = a exp(-b t)` against 13 points that it does not fit exactly (a residual minimum).
    fn decay() -> Written {
        fn t(i: usize) -> f64 {
            0.5 * i as f64
        }
        fn y(i: usize) -> f64 {
            2.5 * (-0.7 * t(i)).exp() + 0.01 * (3.0 * i as f64).sin()
        }
        Written {
            r: |x| (0..13).map(|i| x[0] * (-x[1] * t(i)).exp() - y(i)).collect(),
            j: |x| (0..13).map(|i| vec![(-x[1] * t(i)).exp(), -t(i) * x[0] * (-x[1] * t(i)).exp()]).collect(),
            domain: anywhere,
        }
    }

    /// `r = atan(x)`: root 0, and Newton's steps diverge from `|x| > 1.39`.
    fn arctangent() -> Written {
        Written { r: |x| vec![x[0].atan()], j: |x| vec![vec![1.0 / (1.0 + x[0] * x[0])]], domain: anywhere }
    }

    /// A linear problem `A x - b` (5 x 3, full rank, inconsistent).
    const A: [[f64; 3]; 5] = [[1.0, 0.5, -0.2], [0.3, -1.1, 0.4], [2.0, 0.1, 0.9], [-0.6, 0.8, 1.5], [0.2, 0.2, -0.7]];
    const B: [f64; 5] = [1.0, -0.5, 2.2, 0.3, -0.9];

    fn linear() -> Written {
        Written {
            r: |x| (0..5).map(|i| (0..3).map(|k| A[i][k] * x[k]).sum::<f64>() - B[i]).collect(),
            j: |_| A.iter().map(|row| row.to_vec()).collect(),
            domain: anywhere,
        }
    }

    fn start(p: &Written, x: &[f64]) -> DVector<f64> {
        p.evaluate(x).unwrap()
    }

    const LADDERS: [(&str, Ladder); 2] = [("radial", RADIAL), ("telescope", TELESCOPE)];
    const RUNS: [(&str, Policy); 2] = [("mueller field", MUELLER_FIELD), ("causes", CAUSES)];

    /// Every policy's minimum of the linear problem: the ladders', the runs'.
    fn minima(p: &Written, x0: &[f64]) -> Vec<(&'static str, Solution<DVector<f64>, DMatrix<f64>>)> {
        let mut v: Vec<_> = LADDERS.iter().map(|(n, l)| (*n, ladder(p, x0.to_vec(), l).unwrap())).collect();
        v.extend(RUNS.iter().map(|(n, pol)| (*n, run(p, x0.to_vec(), start(p, x0), pol))));
        v
    }

    #[test]
    fn argmin_tolerance_is_the_square_root_of_epsilon() {
        assert_eq!(ARGMIN_TOL, f64::EPSILON.sqrt());
    }

    /// A Gauss-Newton run is argmin's `GaussNewton` with `gamma` the fraction: the same point,
    /// bit for bit, on a zero-residual, a residual and a linear problem, from near and far
    /// starts, to convergence and cut by the iteration limit, and on a diverging one.
    #[test]
    fn gauss_newton_runs_are_argmins() {
        use argmin::core::{Executor, State};
        use argmin::solver::gaussnewton::GaussNewton;
        let cases = [
            (rosenbrock(), vec![-1.2, 1.0]),
            (decay(), vec![1.0, 0.2]),
            (decay(), vec![6.0, 3.0]),
            (linear(), vec![0.0; 3]),
            (arctangent(), vec![1.5]),
        ];
        for (p, x0) in cases {
            for (fraction, max_iter) in [(1.0, 50), (0.5, 200), (0.25, 200), (0.2, 100), (0.5, 3)] {
                let ours = run(&p, x0.clone(), start(&p, &x0), &gauss_newton(fraction, max_iter));
                let solver = GaussNewton::<f64>::new().with_gamma(fraction).unwrap();
                let res = Executor::new(p, solver)
                    .configure(|s| s.param(DVector::from_row_slice(&x0)).max_iters(max_iter as u64))
                    .run()
                    .unwrap();
                let theirs = res.state().get_best_param().unwrap();
                let bits = |v: &[f64]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
                assert_eq!(
                    bits(&ours.x),
                    bits(theirs.as_slice()),
                    "{x0:?}: fraction {fraction}, {max_iter} iterations"
                );
                assert_eq!(ours.chi2.sqrt(), res.state().get_best_cost());
            }
        }
    }

    /// The linear problem's minimum is the least-squares solution (nalgebra's SVD) under every
    /// policy, to the rounding of the normal equations (the damped runs stop when chi^2 falls by
    /// less than 1e-9 of itself, far below a 1e-6 change in x here).
    #[test]
    fn linear_least_squares_is_the_svd_solution_under_every_policy() {
        let p = linear();
        let a = DMatrix::from_fn(5, 3, |i, k| A[i][k]);
        let want = a.svd(true, true).solve(&DVector::from_row_slice(&B), 1e-14).unwrap();
        for (name, s) in minima(&p, &[0.0; 3]) {
            for k in 0..3 {
                assert!((s.x[k] - want[k]).abs() < 1e-6, "{name}: {:?} vs {want}", s.x);
            }
            assert!(s.chi2.is_finite() && !matches!(s.ending, Ending::Failed(_)), "{name}: {:?}", s.ending);
        }
    }

    /// Rosenbrock's valley from the classic start (-1.2, 1) ends at its minimum (1, 1) under
    /// every policy.
    #[test]
    fn rosenbrock_minimum_is_found_under_every_policy() {
        let p = rosenbrock();
        for (name, s) in minima(&p, &[-1.2, 1.0]) {
            assert!((s.x[0] - 1.0).abs() < 1e-5 && (s.x[1] - 1.0).abs() < 1e-5, "{name}: {:?} ({:?})", s.x, s.ending);
        }
    }

    /// Two parameters that enter only as their sum: the undamped ladders say the data do not
    /// determine their combination, before any inverse (no panic, no NaN); the damped runs reach the minimum chi^2 on the line
    /// `x + y = 7/5` (closed form: 0.4^2 + 0.2^2 = 0.2) at a finite point.
    #[test]
    fn a_singular_problem_is_judged_undetermined() {
        let p = Written {
            r: |x| vec![x[0] + x[1] - 1.0, 2.0 * (x[0] + x[1]) - 3.0],
            j: |_| vec![vec![1.0, 1.0], vec![2.0, 2.0]],
            domain: anywhere,
        };
        for (name, l) in LADDERS {
            match ladder(&p, vec![0.0, 0.0], &l) {
                Err(LsqError::Undetermined(u)) => {
                    assert_eq!(u.free, "a combination of parameter 1 and parameter 2", "{name}");
                    assert!(u.ratio < 1e-15, "{name}: {u}");
                }
                other => panic!("{name}: {other:?}"),
            }
        }
        for (name, pol) in RUNS {
            let s = run(&p, vec![0.0, 0.0], start(&p, &[0.0, 0.0]), &pol);
            assert!((s.chi2 - 0.2).abs() < 1e-9 && s.x.iter().all(|v| v.is_finite()), "{name}: {s:?}");
            assert!((s.x[0] + s.x[1] - 1.4).abs() < 1e-6, "{name}: {:?}", s.x);
        }
        // A parameter the residuals do not depend on: a zero row and column. Marquardt's
        // scaling leaves it zero, so no damped matrix factorizes: the run ends, where it began.
        let q = Written {
            r: |x| vec![x[0] - 1.0, x[0] + 1.0],
            j: |_| vec![vec![1.0, 0.0], vec![1.0, 0.0]],
            domain: anywhere,
        };
        let s = run(&q, vec![0.5, 0.0], start(&q, &[0.5, 0.0]), &MUELLER_FIELD);
        assert_eq!((s.x, s.ending), (vec![0.5, 0.0], Ending::NoDecrease));
        // The additive damping's floor still moves the other parameter to its minimum, x = 0.
        let s = run(&q, vec![0.5, 0.0], start(&q, &[0.5, 0.0]), &CAUSES);
        assert!(s.x[0].abs() < 1e-6 && s.x[1] == 0.0, "{:?}", s.x);
    }

    /// A minimum outside the problem's domain: every Gauss-Newton run steps out of it, and the
    /// ladder says so in the problem's words; a damped run treats the step out as rejected and
    /// stops inside, near the edge.
    #[test]
    fn a_point_outside_the_domain_fails_the_undamped_runs_only() {
        let p = Written { r: |x| vec![x[0] - 3.0], j: |_| vec![vec![1.0]], domain: |x| x[0] <= 2.0 };
        for (name, l) in LADDERS {
            match ladder(&p, vec![0.0], &l) {
                Err(LsqError::Evaluation(w)) => assert!(w.contains("outside the domain"), "{name}: {w}"),
                other => panic!("{name}: {other:?}"),
            }
        }
        for (name, pol) in RUNS {
            let s = run(&p, vec![0.0], start(&p, &[0.0]), &pol);
            assert!(s.x[0] <= 2.0 && s.x[0] > 1.9, "{name}: {:?} ({:?})", s.x, s.ending);
        }
        assert!(matches!(ladder(&p, vec![2.5], &RADIAL), Err(LsqError::Evaluation(_))));
    }

    /// `r = atan(x)` (root 0): Newton's full steps from 1.5 overshoot farther each time until
    /// `|atan x|` stops changing at pi/2 and the norm rule ends the run; its result is its best
    /// point, the start. The radial ladder keeps that run (not worse than the start, argmin's
    /// result kept as it was); the telescope's does not (not lower) and its half steps reach
    /// the root, as the damped runs do.
    #[test]
    fn a_diverging_full_step_run_returns_its_start() {
        let p = arctangent();
        let full = run(&p, vec![1.5], start(&p, &[1.5]), &gauss_newton(1.0, 50));
        assert_eq!((full.x.as_slice(), &full.ending), (&[1.5][..], &Ending::Converged));
        for (name, s) in minima(&p, &[1.5]) {
            let want = if name == "radial" { 1.5 } else { 0.0 };
            assert!((s.x[0] - want).abs() < 1e-8, "{name}: {:?} ({:?})", s.x, s.ending);
        }
    }
}
