//! Built without the `hdf5` or `video` feature, the sources still open and say what is missing
//! (`cargo test -p bwm-data --no-default-features`).

mod common;

#[cfg(not(feature = "hdf5"))]
#[test]
fn hdf5_datasets_say_the_feature_is_missing() {
    let dir = common::tmp_dir("no-hdf5");
    std::fs::write(dir.join("episode0.hdf5"), b"not read").unwrap();
    let e = format!("{:#}", bwm_data::open_dataset(&dir).err().expect("opening must fail"));
    assert!(e.contains("without the `hdf5` feature"), "{e}");
}

#[cfg(not(feature = "video"))]
#[test]
fn video_frames_say_the_feature_is_missing() {
    use bwm_data::CameraSelection;
    let ds = bwm_data::open_dataset(&common::demo_root()).unwrap();
    let e = format!("{:#}", ds.frames(0, 0..1, &CameraSelection::default()).unwrap_err());
    assert!(e.contains("without the `video` feature"), "{e}");
    assert_eq!(ds.vectors(0, &bwm_data::ActionSpec::eef_abs()).unwrap().len(), 143, "actions need no video");
}
