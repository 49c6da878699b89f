//! Episode records, success rates, policy ranking and agreement with reference success rates
//! (Pearson r and mean absolute error over the (policy, task) pairs, and across policies after
//! averaging each policy over its tasks).

use std::collections::BTreeMap;
use std::path::Path;

use anyhow::{ensure, Context, Result};
use serde::Serialize;

/// One line of episodes.jsonl.
#[derive(Debug, Clone, Serialize)]
pub struct EpisodeRecord {
    pub policy: String,
    pub task: String,
    /// Position of the episode within the task.
    pub episode: usize,
    /// Where the episode starts from (dataset episode or x0 file).
    pub source: String,
    pub success: bool,
    /// Frames generated (x0 excluded).
    pub frames: usize,
    pub chunks: usize,
    pub policy_requests: usize,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub success_probability: Option<f64>,
    #[serde(skip_serializing_if = "Option::is_none")]
    pub judge: Option<String>,
    /// Why the episode failed before the judge could see it; such episodes count as failures.
    pub error: Option<String>,
    pub video: Option<String>,
    pub seconds: f64,
    /// The poses that drove the world model, one per generated frame, in its action space before
    /// normalization (the adapter's output): what replaying the episode on the robot, or in the
    /// simulator that the world model stands in for, would command.
    pub actions: Vec<Vec<f32>>,
}

#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct TaskRate {
    pub policy: String,
    pub task: String,
    pub episodes: usize,
    pub successes: usize,
    pub errors: usize,
    pub success_rate: f64,
    pub reference: Option<f64>,
}

#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct PolicyRate {
    pub rank: usize,
    pub policy: String,
    /// Mean of the policy's per-task success rates.
    pub success_rate: f64,
    pub tasks: usize,
    pub episodes: usize,
    pub errors: usize,
    /// Mean of the reference rates over the same tasks, where all of them are given.
    pub reference: Option<f64>,
}

#[derive(Debug, Clone, Serialize, PartialEq)]
pub struct Agreement {
    /// (policy, task) pairs with a reference rate.
    pub pairs: usize,
    pub pearson_r: Option<f64>,
    pub mae: Option<f64>,
    /// Policies whose every task has a reference rate.
    pub policies: usize,
    pub policy_pearson_r: Option<f64>,
    pub policy_mae: Option<f64>,
}

#[derive(Debug, Clone, Serialize)]
pub struct Summary {
    pub rates: Vec<TaskRate>,
    pub policies: Vec<PolicyRate>,
    pub reference: Option<Agreement>,
}

/// Reference success rates from a CSV with a `policy,task,success_rate` header.
pub fn read_reference(path: &Path) -> Result<BTreeMap<(String, String), f64>> {
    let what = || format!("reference {}", path.display());
    let mut rd = csv::ReaderBuilder::new()
        .trim(csv::Trim::All)
        .from_path(path)
        .with_context(what)?;
    let headers = rd.headers().with_context(what)?.clone();
    let col = |name: &str| {
        headers.iter().position(|h| h == name).with_context(|| {
            format!(
                "{}: no '{name}' column (need policy,task,success_rate)",
                what()
            )
        })
    };
    let (p, t, r) = (col("policy")?, col("task")?, col("success_rate")?);
    let mut out = BTreeMap::new();
    for (i, row) in rd.records().enumerate() {
        let row = row.with_context(what)?;
        let line = i + 2;
        let rate: f64 =
            row.get(r).unwrap_or_default().parse().with_context(|| {
                format!("{}: line {line}: success_rate is not a number", what())
            })?;
        ensure!(
            (0.0..=1.0).contains(&rate),
            "{}: line {line}: success_rate {rate} is outside [0, 1]",
            what()
        );
        let key = (
            row.get(p).unwrap_or_default().to_string(),
            row.get(t).unwrap_or_default().to_string(),
        );
        ensure!(
            out.insert(key.clone(), rate).is_none(),
            "{}: line {line}: {}/{} is listed twice",
            what(),
            key.0,
            key.1
        );
    }
    Ok(out)
}

/// Pearson's r; None for fewer than two points or a constant side.
pub fn pearson(xs: &[f64], ys: &[f64]) -> Option<f64> {
    let n = xs.len();
    if n < 2 || n != ys.len() {
        return None;
    }
    let (mx, my) = (
        xs.iter().sum::<f64>() / n as f64,
        ys.iter().sum::<f64>() / n as f64,
    );
    let cov: f64 = xs.iter().zip(ys).map(|(x, y)| (x - mx) * (y - my)).sum();
    let vx: f64 = xs.iter().map(|x| (x - mx).powi(2)).sum();
    let vy: f64 = ys.iter().map(|y| (y - my).powi(2)).sum();
    (vx > 0.0 && vy > 0.0).then(|| cov / (vx * vy).sqrt())
}

pub fn mae(xs: &[f64], ys: &[f64]) -> Option<f64> {
    (!xs.is_empty() && xs.len() == ys.len())
        .then(|| xs.iter().zip(ys).map(|(x, y)| (x - y).abs()).sum::<f64>() / xs.len() as f64)
}

/// Rates per (policy, task) in the given orders, policies ranked by their mean task rate.
pub fn summarize(
    policies: &[String],
    tasks: &[String],
    records: &[EpisodeRecord],
    reference: Option<&BTreeMap<(String, String), f64>>,
) -> Summary {
    let mut rates = Vec::new();
    for p in policies {
        for t in tasks {
            let eps: Vec<&EpisodeRecord> = records
                .iter()
                .filter(|r| &r.policy == p && &r.task == t)
                .collect();
            if eps.is_empty() {
                continue;
            }
            let successes = eps.iter().filter(|r| r.success).count();
            rates.push(TaskRate {
                policy: p.clone(),
                task: t.clone(),
                episodes: eps.len(),
                successes,
                errors: eps.iter().filter(|r| r.error.is_some()).count(),
                success_rate: successes as f64 / eps.len() as f64,
                reference: reference.and_then(|m| m.get(&(p.clone(), t.clone())).copied()),
            });
        }
    }
    let mut ranked: Vec<PolicyRate> = policies
        .iter()
        .filter_map(|p| {
            let mine: Vec<&TaskRate> = rates.iter().filter(|r| &r.policy == p).collect();
            if mine.is_empty() {
                return None;
            }
            let mean = |v: Vec<f64>| v.iter().sum::<f64>() / v.len() as f64;
            let refs: Option<Vec<f64>> = mine.iter().map(|r| r.reference).collect();
            Some(PolicyRate {
                rank: 0,
                policy: p.clone(),
                success_rate: mean(mine.iter().map(|r| r.success_rate).collect()),
                tasks: mine.len(),
                episodes: mine.iter().map(|r| r.episodes).sum(),
                errors: mine.iter().map(|r| r.errors).sum(),
                reference: refs.map(mean),
            })
        })
        .collect();
    ranked.sort_by(|a, b| b.success_rate.total_cmp(&a.success_rate));
    for (i, p) in ranked.iter_mut().enumerate() {
        p.rank = i + 1;
    }
    let agreement = reference.map(|_| {
        let (xs, ys): (Vec<f64>, Vec<f64>) = rates
            .iter()
            .filter_map(|r| r.reference.map(|y| (r.success_rate, y)))
            .unzip();
        let (px, py): (Vec<f64>, Vec<f64>) = ranked
            .iter()
            .filter_map(|p| p.reference.map(|y| (p.success_rate, y)))
            .unzip();
        Agreement {
            pairs: xs.len(),
            pearson_r: pearson(&xs, &ys),
            mae: mae(&xs, &ys),
            policies: px.len(),
            policy_pearson_r: pearson(&px, &py),
            policy_mae: mae(&px, &py),
        }
    });
    Summary {
        rates,
        policies: ranked,
        reference: agreement,
    }
}

fn opt(v: Option<f64>) -> String {
    v.map_or_else(String::new, |v| format!("{v:.6}"))
}

/// A CSV file through the `csv` crate, which quotes names holding commas or quotes.
fn write_csv(path: &Path, header: &[&str], rows: impl IntoIterator<Item = Vec<String>>) -> Result<()> {
    let what = || format!("writing {}", path.display());
    let mut w = csv::Writer::from_path(path).with_context(what)?;
    w.write_record(header).with_context(what)?;
    for row in rows {
        w.write_record(&row).with_context(what)?;
    }
    w.flush().with_context(what)?;
    Ok(())
}

/// success_rates.csv, policies.csv and summary.json in `dir`.
pub fn write(dir: &Path, summary: &Summary) -> Result<()> {
    write_csv(
        &dir.join("success_rates.csv"),
        &["policy", "task", "episodes", "successes", "errors", "success_rate", "reference_success_rate"],
        summary.rates.iter().map(|r| {
            vec![
                r.policy.clone(),
                r.task.clone(),
                r.episodes.to_string(),
                r.successes.to_string(),
                r.errors.to_string(),
                format!("{:.6}", r.success_rate),
                opt(r.reference),
            ]
        }),
    )?;
    write_csv(
        &dir.join("policies.csv"),
        &["rank", "policy", "success_rate", "tasks", "episodes", "errors", "reference_success_rate"],
        summary.policies.iter().map(|p| {
            vec![
                p.rank.to_string(),
                p.policy.clone(),
                format!("{:.6}", p.success_rate),
                p.tasks.to_string(),
                p.episodes.to_string(),
                p.errors.to_string(),
                opt(p.reference),
            ]
        }),
    )?;
    let json = serde_json::to_string_pretty(summary)?;
    std::fs::write(dir.join("summary.json"), json + "\n")
        .with_context(|| format!("writing {}", dir.join("summary.json").display()))?;
    Ok(())
}

/// The summary as a few lines of text.
pub fn render(summary: &Summary) -> String {
    let fmt = |v: Option<f64>, digits: usize| {
        v.map_or_else(|| "n/a".to_string(), |v| format!("{v:.digits$}"))
    };
    let mut out =
        String::from("success rates (policy / task: successes/episodes, errors, reference):\n");
    for r in &summary.rates {
        out += &format!(
            "  {} / {}: {}/{} = {:.3}, {} errors, reference {}\n",
            r.policy,
            r.task,
            r.successes,
            r.episodes,
            r.success_rate,
            r.errors,
            fmt(r.reference, 3)
        );
    }
    out += "policy ranking (mean over tasks):\n";
    for p in &summary.policies {
        out += &format!(
            "  {}. {} {:.3} (reference {})\n",
            p.rank,
            p.policy,
            p.success_rate,
            fmt(p.reference, 3)
        );
    }
    if let Some(a) = &summary.reference {
        out += &format!(
            "agreement with the reference: {} pairs, Pearson r {}, MAE {}; across {} policies, Pearson r {}, MAE {}\n",
            a.pairs,
            fmt(a.pearson_r, 4),
            fmt(a.mae, 4),
            a.policies,
            fmt(a.policy_pearson_r, 4),
            fmt(a.policy_mae, 4)
        );
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rec(policy: &str, task: &str, success: bool, error: bool) -> EpisodeRecord {
        EpisodeRecord {
            policy: policy.into(),
            task: task.into(),
            episode: 0,
            source: String::new(),
            success,
            frames: 4,
            chunks: 1,
            policy_requests: 1,
            success_probability: None,
            judge: None,
            error: error.then(|| "boom".into()),
            video: None,
            seconds: 0.0,
            actions: Vec::new(),
        }
    }

    #[test]
    fn pearson_and_mae_by_hand() {
        // x = [0, 0.5, 1], y = [0.2, 0.4, 0.9]: mean y 0.5; cov = (-0.5)(-0.3) + 0 + 0.5*0.4 = 0.35;
        // vx = 0.5, vy = 0.09 + 0.01 + 0.16 = 0.26; r = 0.35 / sqrt(0.13).
        let r = pearson(&[0.0, 0.5, 1.0], &[0.2, 0.4, 0.9]).unwrap();
        assert!((r - 0.35 / 0.13f64.sqrt()).abs() < 1e-12);
        assert!((mae(&[0.0, 0.5, 1.0], &[0.2, 0.4, 0.9]).unwrap() - 0.4 / 3.0).abs() < 1e-12);
        assert_eq!(pearson(&[1.0], &[1.0]), None);
        assert_eq!(pearson(&[1.0, 1.0], &[0.0, 1.0]), None);
    }

    #[test]
    fn errors_count_as_failures_and_policies_are_ranked() {
        let records = vec![
            rec("a", "t1", true, false),
            rec("a", "t1", false, true),
            rec("a", "t2", true, false),
            rec("b", "t1", true, false),
            rec("b", "t2", false, false),
            rec("b", "t2", false, true),
        ];
        let reference: BTreeMap<_, _> = [
            (("a".into(), "t1".into()), 0.4),
            (("a".into(), "t2".into()), 0.8),
            (("b".into(), "t1".into()), 0.9),
        ]
        .into();
        let s = summarize(
            &["a".into(), "b".into()],
            &["t1".into(), "t2".into()],
            &records,
            Some(&reference),
        );
        let rates: Vec<f64> = s.rates.iter().map(|r| r.success_rate).collect();
        assert_eq!(rates, vec![0.5, 1.0, 1.0, 0.0]);
        assert_eq!(s.rates[0].errors, 1);
        assert_eq!(
            (s.policies[0].policy.as_str(), s.policies[0].success_rate),
            ("a", 0.75)
        );
        assert_eq!(
            (s.policies[1].policy.as_str(), s.policies[1].rank),
            ("b", 2)
        );
        assert_eq!(s.policies[0].reference, Some((0.4 + 0.8) / 2.0));
        assert_eq!(s.policies[1].reference, None, "b/t2 has no reference");
        let a = s.reference.unwrap();
        assert_eq!((a.pairs, a.policies), (3, 1));
        assert!((a.mae.unwrap() - (0.1 + 0.2 + 0.1) / 3.0).abs() < 1e-12);
        assert_eq!(a.pearson_r, pearson(&[0.5, 1.0, 1.0], &[0.4, 0.8, 0.9]));
        assert_eq!(a.policy_pearson_r, None, "one policy");
    }

    #[test]
    fn the_csv_files_quote_names_with_commas_and_read_back() {
        let records = vec![rec("pi0, fast", "open \"drawer\"", true, false), rec("plain", "open \"drawer\"", false, false)];
        let s = summarize(&["pi0, fast".into(), "plain".into()], &["open \"drawer\"".into()], &records, None);
        let dir = bwm_testdir::TestDir::new("eval-report");
        write(dir.path(), &s).unwrap();
        let text = std::fs::read_to_string(dir.path().join("success_rates.csv")).unwrap();
        assert!(text.starts_with("policy,task,episodes,successes,errors,success_rate,reference_success_rate\n"), "{text}");
        let mut reader = csv::Reader::from_path(dir.path().join("success_rates.csv")).unwrap();
        let rows: Vec<Vec<String>> = reader.records().map(|r| r.unwrap().iter().map(String::from).collect()).collect();
        assert_eq!(rows[0], ["pi0, fast", "open \"drawer\"", "1", "1", "0", "1.000000", ""]);
        assert_eq!(rows[1][..2], ["plain", "open \"drawer\""]);
        let mut reader = csv::Reader::from_path(dir.path().join("policies.csv")).unwrap();
        let first = reader.records().next().unwrap().unwrap();
        assert_eq!((&first[0], &first[1]), ("1", "pi0, fast"));
    }
}
