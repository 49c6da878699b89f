//! The openpi observation dict built from the latest frame, and the action chunk read from a
//! policy's reply.

use anyhow::{ensure, Context, Result};
use bwm_data::frames::fit;
use image::imageops;
use image::RgbImage;
use rmpv::Value;

use super::config::{ImageLayout, KeyPath, ObservationConfig};
use crate::msgpack_numpy::{get_path, insert_path, str_map, NdArray};

/// The views of a frame whose `n` camera images are stacked top to bottom.
pub fn split_views(frame: &RgbImage, n: usize) -> Result<Vec<RgbImage>> {
    let (w, h) = frame.dimensions();
    ensure!(
        n > 0 && h % n as u32 == 0,
        "a {w}x{h} frame does not split into {n} views of equal height"
    );
    let vh = h / n as u32;
    Ok((0..n as u32)
        .map(|i| imageops::crop_imm(frame, 0, i * vh, w, vh).to_image())
        .collect())
}

/// `{image keys: uint8 images, state key: float32 [d], prompt key: text}`.
pub fn observation(
    frame: &RgbImage,
    state: &[f32],
    prompt: &str,
    cfg: &ObservationConfig,
) -> Result<Value> {
    let (w, h) = cfg.image_size()?;
    let views = split_views(frame, cfg.image_keys.len())?;
    let mut obs = str_map(vec![]);
    for (key, view) in cfg.image_keys.iter().zip(views) {
        let img = fit(&view, w, h, cfg.image_resize);
        let array = match cfg.image_layout {
            ImageLayout::Hwc => NdArray::from_u8(vec![h as usize, w as usize, 3], img.into_raw())?,
            ImageLayout::Chw => {
                let raw = img.into_raw();
                let plane = (w * h) as usize;
                let mut chw = vec![0u8; raw.len()];
                for (p, px) in raw.chunks_exact(3).enumerate() {
                    for c in 0..3 {
                        chw[c * plane + p] = px[c];
                    }
                }
                NdArray::from_u8(vec![3, h as usize, w as usize], chw)?
            }
        };
        insert_path(&mut obs, &key.parts(), array.to_value())
            .with_context(|| format!("observation key {}", key.display()))?;
    }
    insert_path(
        &mut obs,
        &cfg.state_key.parts(),
        NdArray::from_f32(vec![state.len()], state)?.to_value(),
    )
    .with_context(|| format!("observation key {}", cfg.state_key.display()))?;
    insert_path(&mut obs, &cfg.prompt_key.parts(), Value::from(prompt))
        .with_context(|| format!("observation key {}", cfg.prompt_key.display()))?;
    Ok(obs)
}

/// The action chunk of a reply: a numeric [L, A] array (a single [A] vector counts as L = 1).
pub fn action_rows(reply: &Value, key: &KeyPath) -> Result<Vec<Vec<f32>>> {
    let value = get_path(reply, &key.parts())
        .with_context(|| format!("the policy's reply has no '{}' entry", key.display()))?;
    let array = NdArray::from_value(value)
        .with_context(|| format!("the policy's '{}' is not a numpy array", key.display()))?
        .with_context(|| format!("the policy's '{}'", key.display()))?;
    let (rows, cols) = match array.shape.as_slice() {
        &[l, a] => (l, a),
        &[a] => (1, a),
        s => anyhow::bail!(
            "the policy's '{}' has shape {s:?}; expected [horizon, action_dim]",
            key.display()
        ),
    };
    ensure!(
        cols > 0,
        "the policy's '{}' has no action values ({})",
        key.display(),
        array.describe()
    );
    Ok(array
        .to_f32()
        .chunks(cols)
        .take(rows)
        .map(<[f32]>::to_vec)
        .collect())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::msgpack_numpy::array_at;

    #[test]
    fn views_are_split_resized_and_keyed() {
        let mut frame = RgbImage::new(32, 64);
        for (_, y, p) in frame.enumerate_pixels_mut() {
            *p = if y < 32 {
                image::Rgb([200, 0, 0])
            } else {
                image::Rgb([0, 0, 200])
            };
        }
        let cfg = ObservationConfig {
            image_keys: vec![
                KeyPath::Key("observation/image".into()),
                KeyPath::Path(vec!["images".into(), "wrist".into()]),
            ],
            image_size: "16x8".into(),
            image_resize: bwm_data::ResizeMode::Stretch,
            image_layout: ImageLayout::Chw,
            ..Default::default()
        };
        let obs = observation(&frame, &[1.0, 2.0], "go", &cfg).unwrap();
        let top = array_at(&obs, "observation/image").unwrap();
        assert_eq!(top.shape, vec![3, 8, 16]);
        assert!(
            top.data[..128].iter().all(|&v| v == 200) && top.data[128..].iter().all(|&v| v == 0),
            "red plane first"
        );
        let wrist =
            NdArray::from_value(get_path(&obs, &["images".into(), "wrist".into()]).unwrap())
                .unwrap()
                .unwrap();
        assert!(
            wrist.data[256..].iter().all(|&v| v == 200),
            "bottom view is blue"
        );
        assert_eq!(
            array_at(&obs, "observation/state").unwrap().to_f32(),
            vec![1.0, 2.0]
        );
        assert_eq!(
            crate::msgpack_numpy::map_get(&obs, "prompt").and_then(Value::as_str),
            Some("go")
        );
        assert!(split_views(&frame, 3).is_err());
    }

    #[test]
    fn action_chunks_are_read_from_2d_or_1d_arrays() {
        let reply = str_map(vec![(
            "actions",
            NdArray::from_f32(vec![2, 3], &[1., 2., 3., 4., 5., 6.])
                .unwrap()
                .to_value(),
        )]);
        let key = KeyPath::Key("actions".into());
        assert_eq!(
            action_rows(&reply, &key).unwrap(),
            vec![vec![1., 2., 3.], vec![4., 5., 6.]]
        );
        let reply = str_map(vec![(
            "actions",
            NdArray::from_f32(vec![3], &[1., 2., 3.])
                .unwrap()
                .to_value(),
        )]);
        assert_eq!(action_rows(&reply, &key).unwrap(), vec![vec![1., 2., 3.]]);
        let reply = str_map(vec![("actions", Value::from("x"))]);
        assert!(action_rows(&reply, &key)
            .unwrap_err()
            .to_string()
            .contains("not a numpy array"));
        assert!(action_rows(&str_map(vec![]), &key)
            .unwrap_err()
            .to_string()
            .contains("no 'actions'"));
    }
}
