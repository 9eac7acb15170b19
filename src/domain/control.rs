//! A qualified station's drift control: each check run of a master is charted, statistic by
//! statistic, against limits the qualification study set from that master's own runs (an
//! individuals chart), and judged by the Western Electric rules. A violation means the station no
//! longer measures as it did when qualified.

use serde::{Deserialize, Serialize};

/// What a check run of a master is charted by.
#[derive(Clone, Copy, Debug, PartialEq, Eq, PartialOrd, Ord, Hash, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum CheckStatistic {
    /// The median of the master's corrected heights less its certificate, µm: the station's bias
    /// (a change of lens, lighting or the depth estimator's footing shows here); the median, as a
    /// few misread bins at a coarse station would swing a mean from run to run.
    HeightBias,
    /// The machined crest cone's radius at the end face, µm: where the station puts the part's
    /// surface (a refocus or a moved camera shows here, though heights, a difference of two
    /// depths, do not see it).
    CrestConeRadius,
}

impl CheckStatistic {
    pub fn describe(self) -> &'static str {
        match self {
            Self::HeightBias => "height bias",
            Self::CrestConeRadius => "crest-cone radius",
        }
    }
}

/// One chart's limits: a master's statistic over the study's runs.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct ControlLimits {
    /// The master's serial.
    pub master: String,
    pub statistic: CheckStatistic,
    /// The centre line: the mean over the study's runs, µm.
    pub center_um: f64,
    /// The chart's σ, µm: a third of the 99.73% prediction bound for one new run, s·√(1 + 1/n)·t
    /// (Student's t with n − 1 degrees of freedom at the normal's 3σ tail), so that a check
    /// beyond 3σ is as rare as the rule means although the centre line and s come from a few
    /// runs (from 10 runs t = 4.09: σ is 1.43 s). s is the runs' sample standard deviation, at
    /// least [`MIN_SIGMA_UM`]; the height bias is read with the correction fitted without the
    /// run, as a check run meets it.
    pub sigma_um: f64,
    /// The runs the limits come from.
    pub runs: usize,
    /// Whether checks are judged on it: a statistic whose runs scatter too widely to see the
    /// change it watches for is shown, not judged (its tails would only raise false alarms).
    #[serde(default = "yes")]
    pub charted: bool,
    /// Why it is not judged.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub not_charted_because: Option<String>,
    /// The Western Electric rules its checks are judged by: 1 alone, or 1–4 where the limits come
    /// from at least [`SENSITIZING_MIN_RUNS`] runs.
    #[serde(default = "all_rules")]
    pub rules: Vec<u8>,
}

fn yes() -> bool {
    true
}

fn all_rules() -> Vec<u8> {
    vec![1, 2, 3, 4]
}

/// The fewest study runs whose limits the sensitizing rules (2–4) are used with. Those rules read
/// runs of points against the centre line, and a centre line estimated from n runs is off by
/// σ/√n for every later check alike (from 10 runs, σ/3: the notebook's "Drift control" has what
/// that did to unchanged checks). AIAG's SPC manual asks 20–25 subgroups for Phase I limits.
pub const SENSITIZING_MIN_RUNS: usize = 20;

/// The smallest σ a chart takes, µm: runs that agree better than this (a rendering without noise)
/// would otherwise make any rounding a violation.
pub const MIN_SIGMA_UM: f64 = 0.1;

impl ControlLimits {
    /// Limits from the study runs' values; None with fewer than two.
    pub fn of(master: &str, statistic: CheckStatistic, values_um: &[f64]) -> Option<Self> {
        let n = values_um.len();
        if n < 2 {
            return None;
        }
        let mean = values_um.iter().sum::<f64>() / n as f64;
        let var = values_um.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / (n - 1) as f64;
        Some(Self {
            master: master.into(),
            statistic,
            center_um: mean,
            sigma_um: (var * (1.0 + 1.0 / n as f64)).sqrt().max(MIN_SIGMA_UM)
                * crate::numeric::stats::student_t_like_normal(3.0, n - 1)
                / 3.0,
            runs: n,
            charted: true,
            not_charted_because: None,
            rules: if n >= SENSITIZING_MIN_RUNS { all_rules() } else { vec![1] },
        })
    }

    /// A value in σ from the centre line.
    pub fn z(&self, value_um: f64) -> f64 {
        (value_um - self.center_um) / self.sigma_um
    }
}

/// A check run's reading of one statistic.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct ChartPoint {
    pub statistic: CheckStatistic,
    /// The value, µm.
    pub value_um: f64,
    /// Its distance from the centre line, in σ.
    pub z: f64,
}

/// A rule a check broke: which, on which master's which statistic.
#[derive(Clone, Debug, PartialEq, Serialize, Deserialize, utoipa::ToSchema)]
pub struct Violation {
    pub rule: Rule,
    /// The rule's number (1–4) as the Western Electric handbook counts them.
    pub rule_number: u8,
    pub master: String,
    pub statistic: CheckStatistic,
    /// In words, with the value and the limits.
    pub description: String,
}

/// The Western Electric rules (Western Electric Statistical Quality Control Handbook, 1956), as
/// control charts judge a process against its limits.
#[derive(Clone, Copy, Debug, PartialEq, Eq, Serialize, Deserialize, utoipa::ToSchema)]
#[serde(rename_all = "snake_case")]
pub enum Rule {
    /// 1: one point beyond 3σ.
    OneBeyondThreeSigma,
    /// 2: two of three successive points beyond 2σ, on the same side.
    TwoOfThreeBeyondTwoSigma,
    /// 3: four of five successive points beyond 1σ, on the same side.
    FourOfFiveBeyondOneSigma,
    /// 4: eight successive points on the same side of the centre line.
    EightOnOneSide,
}

impl Rule {
    pub fn number(self) -> u8 {
        match self {
            Self::OneBeyondThreeSigma => 1,
            Self::TwoOfThreeBeyondTwoSigma => 2,
            Self::FourOfFiveBeyondOneSigma => 3,
            Self::EightOnOneSide => 4,
        }
    }

    pub fn describe(self) -> &'static str {
        match self {
            Self::OneBeyondThreeSigma => "one point beyond 3σ",
            Self::TwoOfThreeBeyondTwoSigma => "two of three successive points beyond 2σ on one side",
            Self::FourOfFiveBeyondOneSigma => "four of five successive points beyond 1σ on one side",
            Self::EightOnOneSide => "eight successive points on one side of the centre line",
        }
    }
}

/// The first rule the series `z` (in σ from the centre line, oldest first) breaks at its last
/// point; None when that point leaves the chart in control. Judged at each new point, so that a
/// violation is reported once, by the check that made it.
pub fn western_electric(z: &[f64], sensitizing: bool) -> Option<Rule> {
    let last = *z.last()?;
    if last.abs() > 3.0 {
        return Some(Rule::OneBeyondThreeSigma);
    }
    if !sensitizing {
        return None;
    }
    let side = last.signum();
    if side == 0.0 {
        return None;
    }
    // `m` of the last `n` points beyond `k` σ on the last point's side, the last among them.
    let beyond = |n: usize, m: usize, k: f64| {
        z.len() >= m && last * side > k && z[z.len().saturating_sub(n)..].iter().filter(|v| *v * side > k).count() >= m
    };
    if beyond(3, 2, 2.0) {
        return Some(Rule::TwoOfThreeBeyondTwoSigma);
    }
    if beyond(5, 4, 1.0) {
        return Some(Rule::FourOfFiveBeyondOneSigma);
    }
    if z.len() >= 8 && z[z.len() - 8..].iter().all(|v| v * side > 0.0) {
        return Some(Rule::EightOnOneSide);
    }
    None
}

/// The first violation a new check makes on master `master`'s charts (`limits`, the study's):
/// `earlier` holds that master's earlier checks' points under the same study (oldest first),
/// `points` the new check's. Statistics not charted are not judged.
pub fn judge(
    limits: &[ControlLimits],
    master: &str,
    earlier: &[&[ChartPoint]],
    points: &[ChartPoint],
) -> Option<Violation> {
    points.iter().find_map(|p| {
        let l = limits.iter().find(|l| l.master == master && l.statistic == p.statistic && l.charted)?;
        let mut z: Vec<f64> =
            earlier.iter().filter_map(|c| c.iter().find(|e| e.statistic == p.statistic)).map(|e| e.z).collect();
        z.push(p.z);
        let rule = western_electric(&z, l.rules.len() > 1)?;
        Some(Violation {
            rule,
            rule_number: rule.number(),
            master: master.into(),
            statistic: p.statistic,
            description: format!(
                "Western Electric rule {} ({}) on master {master}'s {}: this check read {:.1} µm, {:+.1}σ from the study's centre line",
                rule.number(),
                rule.describe(),
                p.statistic.describe(),
                p.value_um,
                p.z
            ),
        })
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_point_in_control_breaks_nothing() {
        assert_eq!(western_electric(&[], true), None);
        assert_eq!(western_electric(&[0.5, -1.2, 2.5, -0.3, 1.1], true), None);
        assert_eq!(western_electric(&[2.9], true), None);
    }

    #[test]
    fn each_rule_fires_at_the_point_that_completes_it() {
        assert_eq!(western_electric(&[0.2, -3.1], true), Some(Rule::OneBeyondThreeSigma));
        assert_eq!(western_electric(&[2.1, 0.3, 2.2], true), Some(Rule::TwoOfThreeBeyondTwoSigma));
        // Two beyond 2σ but on opposite sides: not rule 2.
        assert_eq!(western_electric(&[-2.1, 0.3, 2.2], true), None);
        // Beyond 2σ twice, but not within three points.
        assert_eq!(western_electric(&[2.1, 0.3, -0.4, 2.2], true), None);
        assert_eq!(western_electric(&[1.2, 1.5, 0.4, 1.1, 1.3], true), Some(Rule::FourOfFiveBeyondOneSigma));
        assert_eq!(western_electric(&[1.2, 1.5, 0.4, -1.1, 1.3], true), None);
        assert_eq!(western_electric(&[0.1, 0.3, 0.2, 0.9, 0.4, 0.2, 0.6, 0.1], true), Some(Rule::EightOnOneSide));
        assert_eq!(western_electric(&[0.1, 0.3, 0.2, 0.9, 0.4, 0.2, 0.6], true), None);
        assert_eq!(western_electric(&[0.1, 0.3, 0.2, -0.9, 0.4, 0.2, 0.6, 0.1], true), None);
    }

    #[test]
    fn limits_from_few_runs_judge_by_rule_one_alone() {
        assert_eq!(western_electric(&[2.1, 0.3, 2.2], false), None);
        assert_eq!(western_electric(&[0.1, 0.3, 0.2, 0.9, 0.4, 0.2, 0.6, 0.1], false), None);
        assert_eq!(western_electric(&[0.1, 3.2], false), Some(Rule::OneBeyondThreeSigma));
        let values: Vec<f64> = (0..10).map(|i| i as f64).collect();
        assert_eq!(ControlLimits::of("M-1", CheckStatistic::HeightBias, &values).unwrap().rules, vec![1]);
        let values: Vec<f64> = (0..SENSITIZING_MIN_RUNS).map(|i| i as f64).collect();
        assert_eq!(ControlLimits::of("M-1", CheckStatistic::HeightBias, &values).unwrap().rules, vec![1, 2, 3, 4]);
    }

    #[test]
    fn a_violation_is_reported_by_the_point_that_makes_it_only() {
        // The last point is back in control: the earlier excursion was reported when it happened.
        assert_eq!(western_electric(&[3.5, 0.2], true), None);
        assert_eq!(western_electric(&[2.1, 2.2, -0.5], true), None);
    }

    #[test]
    fn a_check_is_judged_with_its_charts_history() {
        let point = |statistic, z| ChartPoint { statistic, value_um: 10.0 * z, z };
        let runs: Vec<f64> = (0..25).map(|i| (i % 5) as f64).collect();
        let mut limits = vec![
            ControlLimits::of("M-1", CheckStatistic::HeightBias, &runs).unwrap(),
            ControlLimits::of("M-1", CheckStatistic::CrestConeRadius, &runs).unwrap(),
        ];
        let (first, second) = ([point(CheckStatistic::HeightBias, 2.4)], [point(CheckStatistic::HeightBias, 0.1)]);
        let history: Vec<&[ChartPoint]> = vec![&first, &second];
        assert_eq!(judge(&limits, "M-1", &history, &[point(CheckStatistic::HeightBias, 0.5)]), None);
        let v = judge(
            &limits,
            "M-1",
            &history,
            &[point(CheckStatistic::CrestConeRadius, 0.5), point(CheckStatistic::HeightBias, 2.2)],
        )
        .unwrap();
        assert_eq!((v.rule_number, v.statistic), (2, CheckStatistic::HeightBias));
        assert!(v.description.contains("rule 2") && v.description.contains("M-1"), "{}", v.description);
        let v = judge(&limits, "M-1", &[], &[point(CheckStatistic::CrestConeRadius, -11.5)]).unwrap();
        assert_eq!(v.rule, Rule::OneBeyondThreeSigma);
        // Another master's chart, or a statistic shown but not charted, judges nothing.
        assert_eq!(judge(&limits, "M-2", &[], &[point(CheckStatistic::CrestConeRadius, -11.5)]), None);
        limits[1].charted = false;
        assert_eq!(judge(&limits, "M-1", &[], &[point(CheckStatistic::CrestConeRadius, -11.5)]), None);
    }

    #[test]
    fn limits_take_the_runs_mean_and_standard_deviation() {
        let l = ControlLimits::of("M-1", CheckStatistic::HeightBias, &[1.0, 3.0, 2.0, 2.0]).unwrap();
        assert_eq!(l.center_um, 2.0);
        let t = crate::numeric::stats::student_t_like_normal(3.0, 3);
        assert!((l.sigma_um - (2.0f64 / 3.0 * 1.25).sqrt() * t / 3.0).abs() < 1e-12);
        assert!((l.z(4.0) - 2.0 / l.sigma_um).abs() < 1e-12);
        assert_eq!(ControlLimits::of("M-1", CheckStatistic::HeightBias, &[1.0]), None);
        let flat = ControlLimits::of("M-1", CheckStatistic::CrestConeRadius, &[5.0, 5.0]).unwrap();
        assert!(
            (flat.sigma_um - MIN_SIGMA_UM * crate::numeric::stats::student_t_like_normal(3.0, 1) / 3.0).abs() < 1e-12
        );
    }
}
