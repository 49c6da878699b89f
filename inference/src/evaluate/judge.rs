//! Success judges: an HTTP endpoint (frames POSTed as msgpack-numpy, a JSON probability back)
//! or per-task colour rules evaluated here.

use std::time::Duration;

use anyhow::{anyhow, ensure, Context, Result};
use image::RgbImage;
use rmpv::Value;

use super::config::{ColorRule, JudgeConfig, JudgeKind, Presence};
use crate::msgpack_numpy::{encode, str_map, NdArray};

#[derive(Debug, Clone, PartialEq)]
pub struct Verdict {
    pub success: bool,
    /// The HTTP judge's success probability.
    pub probability: Option<f64>,
    /// What was measured, for the episode record.
    pub detail: String,
}

/// What the judge is told besides the frames.
pub struct Subject<'a> {
    pub policy: &'a str,
    pub task: &'a str,
    pub prompt: &'a str,
    pub episode: usize,
    pub rules: &'a [ColorRule],
    /// The frames end the episode (its horizon reached): an HTTP judge is told so (`final`), so
    /// that a success reached in the last frames counts although no frames follow it.
    pub ends_episode: bool,
}

pub enum Judge {
    Http {
        url: String,
        threshold: f64,
        max_frames: Option<usize>,
        agent: ureq::Agent,
    },
    Rules,
}

impl Judge {
    pub fn new(cfg: &JudgeConfig) -> Result<Self> {
        Ok(match cfg.kind {
            JudgeKind::Http => Judge::Http {
                url: cfg.url.clone().context("judge.url")?,
                threshold: cfg.threshold,
                max_frames: cfg.max_frames,
                agent: ureq::AgentBuilder::new()
                    .timeout(Duration::from_secs_f64(cfg.timeout_s))
                    .build(),
            },
            JudgeKind::Rules => Judge::Rules,
        })
    }

    pub fn describe(&self) -> String {
        match self {
            Judge::Http { url, threshold, .. } => {
                format!("HTTP judge {url} (success at p >= {threshold})")
            }
            Judge::Rules => "per-task colour rules".into(),
        }
    }

    /// Judges the frames generated so far (x0 excluded).
    pub fn judge(&self, frames: &[RgbImage], subject: &Subject) -> Result<Verdict> {
        ensure!(!frames.is_empty(), "no frames to judge");
        match self {
            Judge::Rules => Ok(check_rules(subject.rules, frames)),
            Judge::Http {
                url,
                threshold,
                max_frames,
                agent,
            } => {
                let picked = pick_frames(frames.len(), *max_frames);
                let (w, h) = frames[0].dimensions();
                let mut data = Vec::with_capacity(picked.len() * (w * h * 3) as usize);
                for &i in &picked {
                    data.extend_from_slice(frames[i].as_raw());
                }
                let body = encode(&str_map(vec![
                    (
                        "frames",
                        NdArray::from_u8(vec![picked.len(), h as usize, w as usize, 3], data)?
                            .to_value(),
                    ),
                    ("task", Value::from(subject.task)),
                    ("prompt", Value::from(subject.prompt)),
                    ("policy", Value::from(subject.policy)),
                    ("episode", Value::from(subject.episode as u64)),
                    ("final", Value::from(subject.ends_episode)),
                ]));
                let reply = match agent
                    .post(url)
                    .set("Content-Type", "application/msgpack")
                    .send_bytes(&body)
                {
                    Ok(r) => r
                        .into_string()
                        .with_context(|| format!("judge {url}: reading the reply"))?,
                    Err(ureq::Error::Status(code, r)) => {
                        let text = r.into_string().unwrap_or_default();
                        return Err(anyhow!("judge {url} answered HTTP {code}: {}", text.trim()));
                    }
                    Err(e) => return Err(anyhow!("judge {url}: {e}")),
                };
                let json: serde_json::Value = serde_json::from_str(&reply)
                    .with_context(|| format!("judge {url}: reply is not JSON: {}", reply.trim()))?;
                let p = json
                    .get("success_probability")
                    .and_then(serde_json::Value::as_f64)
                    .with_context(|| {
                        format!(
                            "judge {url}: expected {{\"success_probability\": p}}, got {}",
                            reply.trim()
                        )
                    })?;
                ensure!(
                    (0.0..=1.0).contains(&p),
                    "judge {url}: success_probability {p} is outside [0, 1]"
                );
                Ok(Verdict {
                    success: p >= *threshold,
                    probability: Some(p),
                    detail: format!("p = {p:.3} on {} frames", picked.len()),
                })
            }
        }
    }
}

/// At most `max` frame indices, evenly spaced, the last frame always included.
fn pick_frames(n: usize, max: Option<usize>) -> Vec<usize> {
    match max {
        Some(m) if m < n => (0..m).map(|i| ((i + 1) * n).div_ceil(m) - 1).collect(),
        _ => (0..n).collect(),
    }
}

/// Share of the rule's region whose pixels fall inside its RGB range.
pub fn color_fraction(frame: &RgbImage, rule: &ColorRule) -> f64 {
    let (w, h) = frame.dimensions();
    let [l, t, r, b] = rule.roi;
    let x0 = ((l * w as f64).floor() as u32).min(w.saturating_sub(1));
    let y0 = ((t * h as f64).floor() as u32).min(h.saturating_sub(1));
    let x1 = ((r * w as f64).ceil() as u32).clamp(x0 + 1, w.max(x0 + 1));
    let y1 = ((b * h as f64).ceil() as u32).clamp(y0 + 1, h.max(y0 + 1));
    let mut hits = 0u64;
    let mut total = 0u64;
    for y in y0..y1.min(h) {
        for x in x0..x1.min(w) {
            let p = frame.get_pixel(x, y).0;
            total += 1;
            if (0..3).all(|c| rule.rgb_min[c] <= p[c] && p[c] <= rule.rgb_max[c]) {
                hits += 1;
            }
        }
    }
    if total == 0 {
        0.0
    } else {
        hits as f64 / total as f64
    }
}

/// Success when every rule holds on each of its last frames; fewer frames than a rule looks at
/// do not satisfy it yet.
pub fn check_rules(rules: &[ColorRule], frames: &[RgbImage]) -> Verdict {
    let mut success = !rules.is_empty();
    let mut details = Vec::new();
    for (i, rule) in rules.iter().enumerate() {
        if frames.len() < rule.last_frames {
            success = false;
            details.push(format!(
                "rule {i}: needs {} frames, {} so far",
                rule.last_frames,
                frames.len()
            ));
            continue;
        }
        let fractions: Vec<f64> = frames[frames.len() - rule.last_frames..]
            .iter()
            .map(|f| color_fraction(f, rule))
            .collect();
        let holds = fractions.iter().all(|&f| match rule.expect {
            Presence::Present => f >= rule.min_fraction,
            Presence::Absent => f < rule.min_fraction,
        });
        success &= holds;
        let shown: Vec<String> = fractions.iter().map(|f| format!("{f:.3}")).collect();
        details.push(format!(
            "rule {i} ({:?} >= {}): fractions [{}] -> {}",
            rule.expect,
            rule.min_fraction,
            shown.join(", "),
            if holds { "holds" } else { "fails" }
        ));
    }
    Verdict {
        success,
        probability: None,
        detail: details.join("; "),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A grey frame with a red square at (x, y) of the given side.
    fn frame(square: Option<(u32, u32, u32)>) -> RgbImage {
        let mut f = RgbImage::from_pixel(40, 20, image::Rgb([90, 90, 90]));
        if let Some((x, y, s)) = square {
            for j in y..y + s {
                for i in x..x + s {
                    f.put_pixel(i, j, image::Rgb([220, 30, 20]));
                }
            }
        }
        f
    }

    fn red(expect: Presence, roi: [f64; 4], last: usize, min_fraction: f64) -> ColorRule {
        ColorRule {
            expect,
            rgb_min: [180, 0, 0],
            rgb_max: [255, 80, 80],
            roi,
            last_frames: last,
            min_fraction,
        }
    }

    #[test]
    fn colour_fraction_counts_the_region_only() {
        let f = frame(Some((0, 0, 10)));
        // Left half (20x20 = 400 pixels) holds the 100 red ones.
        assert_eq!(
            color_fraction(&f, &red(Presence::Present, [0.0, 0.0, 0.5, 1.0], 1, 0.1)),
            0.25
        );
        assert_eq!(
            color_fraction(&f, &red(Presence::Present, [0.5, 0.0, 1.0, 1.0], 1, 0.1)),
            0.0
        );
        assert_eq!(
            color_fraction(&f, &red(Presence::Present, [0.0, 0.0, 1.0, 1.0], 1, 0.1)),
            100.0 / 800.0
        );
    }

    #[test]
    fn rules_need_every_one_of_the_last_frames() {
        let left = [0.0, 0.0, 0.5, 1.0];
        let present = red(Presence::Present, left, 2, 0.2);
        let frames = vec![
            frame(None),
            frame(Some((0, 0, 10))),
            frame(Some((2, 2, 10))),
        ];
        assert!(check_rules(std::slice::from_ref(&present), &frames).success);
        assert!(
            !check_rules(std::slice::from_ref(&present), &frames[..2]).success,
            "frame 0 of the last two has no red"
        );
        assert!(
            !check_rules(std::slice::from_ref(&present), &frames[2..]).success,
            "fewer frames than last_frames"
        );
        let absent = red(Presence::Absent, [0.5, 0.0, 1.0, 1.0], 3, 0.01);
        assert!(check_rules(&[present.clone(), absent.clone()], &frames).success);
        let moved = vec![
            frame(None),
            frame(Some((0, 0, 10))),
            frame(Some((25, 5, 10))),
        ];
        let v = check_rules(&[present, absent], &moved);
        assert!(!v.success && v.detail.contains("fails"), "{}", v.detail);
        assert!(!check_rules(&[], &moved).success, "no rules, no success");
    }

    #[test]
    fn frames_are_subsampled_evenly_keeping_the_last() {
        assert_eq!(pick_frames(5, None), vec![0, 1, 2, 3, 4]);
        assert_eq!(pick_frames(8, Some(4)), vec![1, 3, 5, 7]);
        assert_eq!(pick_frames(3, Some(8)), vec![0, 1, 2]);
        assert_eq!(pick_frames(10, Some(1)), vec![9]);
    }
}
