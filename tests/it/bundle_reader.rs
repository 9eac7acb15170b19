//! One test per class of bad bundle, each asserting the stable code and that the message names the
//! culprit (field or file); plus the good paths: directory, zip, tar, nested folder, PNG and TIFF
//! in 8 and 16 bits, gray and RGB.

use crate::common::{Scratch, ci_bundle, walk};
use crestscan::bundle::{Bundle, BundleError, FrameCheck, Limits, OpenOptions};
use crestscan::domain::thread::ConnectionTable;
use crestscan::problem::ErrorCode;
use serde_json::json;
use std::io::Write;
use std::path::Path;

fn open(path: &Path) -> Result<Bundle, BundleError> {
    Bundle::open(path, &ConnectionTable::api5b(), OpenOptions::default())
}

fn open_with(path: &Path, limits: Limits) -> Result<Bundle, BundleError> {
    Bundle::open(path, &ConnectionTable::api5b(), OpenOptions { limits, frame_check: FrameCheck::Headers, name: None })
}

/// Opens, expects an error with `code`, and checks the message names every `culprit`.
fn expect_error(result: Result<Bundle, BundleError>, code: &str, culprits: &[&str]) -> String {
    let err = result.expect_err("bundle should be refused");
    let message = err.to_string();
    assert_eq!(err.code().name(), code, "{message}");
    for culprit in culprits {
        assert!(message.contains(culprit), "message {message:?} does not name {culprit:?}");
    }
    message
}

fn first_frame(s: &Scratch) -> String {
    s.manifest()["views"][0]["frames"][0]["file"].as_str().unwrap().to_string()
}

#[test]
fn the_ci_bundle_opens_as_a_directory_and_decodes() {
    let bundle = open(ci_bundle()).unwrap();
    assert_eq!(bundle.views.len(), 3);
    assert_eq!(bundle.part.connection.as_deref(), Some("BC 4-1/2"));
    assert!((bundle.part.lc_mm - 31.839).abs() < 1e-3);
    let frame = bundle.read_frame(0, 0).unwrap();
    assert_eq!((frame.width, frame.height, frame.channels), (384, 160, 3));
    assert!(frame.samples.values().iter().all(|v| (0.0..=1.0).contains(v)));
    let full = Bundle::open(
        ci_bundle(),
        &ConnectionTable::api5b(),
        OpenOptions { frame_check: FrameCheck::Decode, ..Default::default() },
    );
    assert!(full.is_ok());
}

#[test]
fn unknown_format_version() {
    let s = Scratch::new();
    s.edit(|m| m["format"] = json!("crestscan.focal-stack/2"));
    expect_error(open(s.path()), "unsupported_format_version", &["format", "crestscan.focal-stack/2"]);
}

#[test]
fn malformed_field_is_named_by_its_path() {
    let s = Scratch::new();
    s.edit(|m| m["views"][1]["pose"]["angle_deg"] = json!("north"));
    expect_error(open(s.path()), "invalid_manifest", &["views[1].pose.angle_deg"]);
    s.edit(|m| m["views"][1]["pose"]["angle_deg"] = json!(1e300));
    expect_error(open(s.path()), "invalid_manifest", &["views[1].pose.angle_deg", "outside"]);
    std::fs::write(s.path().join("manifest.json"), b"{\"format\": \"crestscan.focal-stack/1\", ").unwrap();
    expect_error(open(s.path()), "invalid_manifest", &["manifest.json", "line 1"]);
}

#[test]
fn missing_frame() {
    let s = Scratch::new();
    let file = first_frame(&s);
    std::fs::remove_file(s.path().join(&file)).unwrap();
    expect_error(open(s.path()), "missing_file", &[&file]);
}

#[test]
fn unreadable_frame() {
    let s = Scratch::new();
    let file = first_frame(&s);
    std::fs::write(s.path().join(&file), b"\x89PNG\r\n\x1a\n not really a png").unwrap();
    expect_error(open(s.path()), "unreadable_frame", &[&file]);
    // A frame whose header is fine but whose data is cut off is found when decoded, by name.
    let s = Scratch::new();
    let bytes = std::fs::read(s.path().join(&file)).unwrap();
    std::fs::write(s.path().join(&file), &bytes[..bytes.len() / 2]).unwrap();
    let bundle = open(s.path()).expect("header still reads");
    let err = bundle.read_frame(0, 0).unwrap_err();
    assert_eq!(err.code().name(), "unreadable_frame");
    assert!(err.to_string().contains(&file));
    let full = Bundle::open(
        s.path(),
        &ConnectionTable::api5b(),
        OpenOptions { frame_check: FrameCheck::Decode, ..Default::default() },
    );
    expect_error(full, "unreadable_frame", &[&file]);
}

fn write_png(path: &Path, width: u32, height: u32, sixteen: bool, gray: bool) {
    let channels = if gray { 1 } else { 3 };
    let n = (width * height * channels) as usize;
    let image: image::DynamicImage = match (sixteen, gray) {
        (false, false) => {
            image::RgbImage::from_raw(width, height, (0..n).map(|i| (i % 251) as u8).collect()).unwrap().into()
        }
        (false, true) => {
            image::GrayImage::from_raw(width, height, (0..n).map(|i| (i % 251) as u8).collect()).unwrap().into()
        }
        (true, false) => image::ImageBuffer::<image::Rgb<u16>, _>::from_raw(
            width,
            height,
            (0..n).map(|i| (i * 97 % 65521) as u16).collect(),
        )
        .unwrap()
        .into(),
        (true, true) => image::ImageBuffer::<image::Luma<u16>, _>::from_raw(
            width,
            height,
            (0..n).map(|i| (i * 97 % 65521) as u16).collect(),
        )
        .unwrap()
        .into(),
    };
    image.save(path).unwrap();
}

#[test]
fn mixed_sizes_within_a_view() {
    let s = Scratch::new();
    let file = s.manifest()["views"][0]["frames"][4]["file"].as_str().unwrap().to_string();
    write_png(&s.path().join(&file), 200, 160, false, false);
    let message = expect_error(open(s.path()), "inconsistent_frames", &[&file, "200×160"]);
    assert!(message.contains("384×160"), "{message}");
}

#[test]
fn mixed_bit_depths_within_a_view() {
    let s = Scratch::new();
    let file = s.manifest()["views"][2]["frames"][3]["file"].as_str().unwrap().to_string();
    write_png(&s.path().join(&file), 384, 160, true, false);
    expect_error(open(s.path()), "inconsistent_frames", &[&file, "16-bit"]);
}

#[test]
fn non_monotonic_offsets() {
    let s = Scratch::new();
    s.edit(|m| m["views"][1]["frames"][5]["offset_mm"] = json!(-5.0));
    expect_error(open(s.path()), "invalid_offsets", &["views[1].frames[5].offset_mm", "grow"]);
}

#[test]
fn duplicate_offsets() {
    let s = Scratch::new();
    s.edit(|m| {
        let previous = m["views"][0]["frames"][2]["offset_mm"].clone();
        m["views"][0]["frames"][3]["offset_mm"] = previous;
    });
    expect_error(open(s.path()), "invalid_offsets", &["views[0].frames[3].offset_mm", "duplicates"]);
}

#[test]
fn fewer_than_three_frames() {
    let s = Scratch::new();
    s.edit(|m| m["views"][2]["frames"].as_array_mut().unwrap().truncate(2));
    expect_error(open(s.path()), "too_few_frames", &["views[2].frames", "at least 3"]);
}

#[test]
fn paths_that_escape_the_bundle() {
    for evil in ["../outside.png", "/etc/passwd.png", "a000-z00/../../x.png", "C:\\frames\\x.png"] {
        let s = Scratch::new();
        s.edit(|m| m["views"][0]["frames"][0]["file"] = json!(evil));
        expect_error(open(s.path()), "unsafe_path", &[evil]);
    }
}

#[cfg(unix)]
#[test]
fn symlinks_are_refused() {
    let outside = tempfile::tempdir().unwrap();
    let s = Scratch::new();
    let file = first_frame(&s);
    let target = outside.path().join("elsewhere.png");
    std::fs::copy(s.path().join(&file), &target).unwrap();
    std::fs::remove_file(s.path().join(&file)).unwrap();
    std::os::unix::fs::symlink(&target, s.path().join(&file)).unwrap();
    expect_error(open(s.path()), "unsafe_path", &[&file, "symbolic link"]);
    // A symlinked folder is refused too.
    let s = Scratch::new();
    let folder = file.split('/').next().unwrap().to_string();
    let moved = outside.path().join("moved");
    std::fs::rename(s.path().join(&folder), &moved).unwrap();
    std::os::unix::fs::symlink(&moved, s.path().join(&folder)).unwrap();
    expect_error(open(s.path()), "unsafe_path", &[&folder]);
}

#[test]
fn bad_optics_name_the_field() {
    let cases = [
        ("f_number", json!(-2.8), "optics.f_number"),
        ("focus_distance_mm", json!(40.0), "optics.focus_distance_mm"),
        ("pixel_pitch_um", json!(0.0), "optics.pixel_pitch_um"),
        ("f_number", json!("NaN"), "optics.f_number"),
        ("f_number", json!(1e308), "optics.f_number"),
        ("pixel_pitch_um", json!(1e300), "optics.pixel_pitch_um"),
        ("projection", json!("fisheye"), "optics.projection"),
    ];
    for (field, value, culprit) in cases {
        let s = Scratch::new();
        s.edit(|m| m["optics"][field] = value.clone());
        expect_error(open(s.path()), "invalid_optics", &[culprit]);
    }
    // Inconsistent: a lens cannot focus closer than its focal length.
    let s = Scratch::new();
    s.edit(|m| {
        m["optics"]["focal_length_mm"] = json!(300.0);
    });
    expect_error(open(s.path()), "invalid_optics", &["focus_distance_mm", "focal_length_mm"]);
    // Telecentric needs a magnification.
    let s = Scratch::new();
    s.edit(|m| m["optics"]["projection"] = json!("telecentric"));
    expect_error(open(s.path()), "invalid_optics", &["optics.magnification"]);
    // ... and no focal length (bundle.md describes it by its magnification): null or absent.
    s.edit(|m| {
        m["optics"]["magnification"] = json!(0.3);
        m["optics"]["focal_length_mm"] = json!(null);
    });
    assert!(open(s.path()).is_ok());
    s.edit(|m| {
        m["optics"].as_object_mut().unwrap().remove("focal_length_mm");
    });
    assert!(open(s.path()).is_ok());
    // A perspective projection does need one.
    s.edit(|m| m["optics"]["projection"] = json!("perspective"));
    expect_error(open(s.path()), "invalid_optics", &["optics.focal_length_mm", "perspective"]);
}

/// A manifest whose inspection would need more memory than the caps allow is refused before any
/// work, naming what makes it large: a mistyped pixel pitch or pose, or frames too many or large.
#[test]
fn work_beyond_the_caps_is_refused_naming_its_cause() {
    let s = Scratch::new();
    // 12 µm typed as 0.012 µm: object pixels a thousand times finer over the whole circumference.
    s.edit(|m| m["optics"]["pixel_pitch_um"] = json!(0.012));
    expect_error(open(s.path()), "inspection_too_large", &["optics.pixel_pitch_um:", "0.0408 µm", "surface"]);
    let s = Scratch::new();
    // One view's axial pose 100 m down the pipe.
    s.edit(|m| m["views"][1]["pose"]["axial_mm"] = json!(1e5));
    expect_error(open(s.path()), "inspection_too_large", &["views[1].pose.axial_mm:", "100000"]);
    // A custom pipe 100 m across.
    let s = Scratch::new();
    s.edit(|m| m["part"]["thread"] = json!({ "pipe_od_mm": 1e5 }));
    expect_error(open(s.path()), "inspection_too_large", &["part.thread.pipe_od_mm:", "314159.3 mm circumference"]);
    // The ci views are 18 frames of 384×160: 1.1 M stack samples, 0.18 M view pixels.
    let s = Scratch::new();
    let caps = Limits { max_stack_samples: 1_000_000, ..Limits::default() };
    expect_error(
        open_with(s.path(), caps),
        "inspection_too_large",
        &["views[0].frames:", "18 frames of 384×160", "1105920"],
    );
    let caps = Limits { max_view_pixels: 100_000, ..Limits::default() };
    expect_error(open_with(s.path(), caps), "inspection_too_large", &["views:", "3 views of 184320 pixels"]);
    let caps = Limits { max_stack_samples: 1_105_920, max_view_pixels: 184_320, ..Limits::default() };
    assert!(open_with(s.path(), caps).is_ok(), "the caps are inclusive");
}

#[test]
fn unknown_connection_and_custom_threads() {
    let s = Scratch::new();
    s.edit(|m| m["part"]["connection"] = json!("EUE 2-7/8"));
    expect_error(open(s.path()), "unknown_connection", &["part.connection", "EUE 2-7/8"]);
    // With a complete custom form the designation is only a label.
    s.edit(|m| {
        m["part"]["thread"] = json!({ "family": "round", "pitch_mm": 3.175, "thread_height_mm": 1.81,
            "height_tolerance_mm": 0.051, "taper_on_diameter": 0.0625, "pipe_od_mm": 88.9, "lc_mm": 40.0 })
    });
    let bundle = open(s.path()).unwrap();
    assert_eq!(bundle.part.connection.as_deref(), Some("EUE 2-7/8"));
    assert_eq!(bundle.part.lc_mm, 40.0);
    // An incomplete one names the missing field.
    s.edit(|m| m["part"]["thread"].as_object_mut().unwrap().remove("lc_mm").map(|_| ()).unwrap());
    expect_error(open(s.path()), "invalid_thread", &["part.thread.lc_mm"]);
    // Overrides on a table connection (the seed's premium form on a BC 4-1/2 pipe).
    s.edit(|m| {
        m["part"]["connection"] = json!("BC 4-1/2");
        m["part"]["thread"] = json!({ "thread_height_mm": 1.0, "height_tolerance_mm": 0.03, "lc_mm": 35.8 });
    });
    let bundle = open(s.path()).unwrap();
    assert_eq!(bundle.part.form.height_mm, 1.0);
    assert_eq!(bundle.part.lc_mm, 35.8);
    assert_eq!(bundle.part.form.pitch_mm, 5.08);
    // A form that cannot exist.
    s.edit(|m| m["part"]["thread"] = json!({ "thread_height_mm": 30.0 }));
    expect_error(open(s.path()), "invalid_thread", &["part.thread"]);
}

fn zip_dir(dir: &Path, zip_path: &Path, folder: Option<&str>) {
    let file = std::fs::File::create(zip_path).unwrap();
    let mut zip = zip::ZipWriter::new(file);
    let options = zip::write::SimpleFileOptions::default().compression_method(zip::CompressionMethod::Stored);
    for path in walk(dir) {
        let rel = path.strip_prefix(dir).unwrap().to_string_lossy().replace('\\', "/");
        let name = match folder {
            Some(f) => format!("{f}/{rel}"),
            None => rel,
        };
        zip.start_file(name, options).unwrap();
        zip.write_all(&std::fs::read(&path).unwrap()).unwrap();
    }
    zip.finish().unwrap();
}

fn tar_dir(dir: &Path, tar_path: &Path, folder: Option<&str>) {
    let mut builder = tar::Builder::new(std::fs::File::create(tar_path).unwrap());
    for path in walk(dir) {
        let rel = path.strip_prefix(dir).unwrap();
        let name = match folder {
            Some(f) => Path::new(f).join(rel),
            None => rel.to_path_buf(),
        };
        builder.append_path_with_name(&path, name).unwrap();
    }
    builder.finish().unwrap();
}

#[test]
fn zip_and_tar_archives_at_the_root_or_in_one_folder() {
    let s = Scratch::new();
    let out = tempfile::tempdir().unwrap();
    for folder in [None, Some("P-000123")] {
        let zip_path = out.path().join("b.zip");
        zip_dir(s.path(), &zip_path, folder);
        let bundle = open(&zip_path).unwrap();
        assert_eq!(bundle.views.len(), 3);
        let from_zip = bundle.read_frame(2, 7).unwrap();
        let tar_path = out.path().join("b.tar");
        tar_dir(s.path(), &tar_path, folder);
        let bundle = open(&tar_path).unwrap();
        assert_eq!(from_zip, bundle.read_frame(2, 7).unwrap());
    }
    // Two top-level folders: no bundle root.
    let zip_path = out.path().join("two.zip");
    let mut zip = zip::ZipWriter::new(std::fs::File::create(&zip_path).unwrap());
    let options = zip::write::SimpleFileOptions::default();
    for name in ["a/manifest.json", "b/other.txt"] {
        zip.start_file(name, options).unwrap();
        zip.write_all(b"{}").unwrap();
    }
    zip.finish().unwrap();
    expect_error(open(&zip_path), "missing_file", &["manifest.json"]);
    // Not an archive at all.
    let junk = out.path().join("junk.bin");
    std::fs::write(&junk, vec![7u8; 4096]).unwrap();
    expect_error(open(&junk), "invalid_archive", &["junk.bin"]);
}

/// Issue 49: a `.tar.gz` reads as its tar does; an archive made from outside the bundle's folder
/// (`tar -cf x.tar out/ci`) is answered with the `tar -C` that makes it right; a gzip bomb hits the
/// caps a zip's does.
#[test]
fn gzipped_tars_read_and_a_too_deep_bundle_gets_the_tar_c_hint() {
    let s = Scratch::new();
    let out = tempfile::tempdir().unwrap();
    let tar_path = out.path().join("b.tar");
    tar_dir(s.path(), &tar_path, Some("P-000123"));
    let gz_path = out.path().join("b.tar.gz");
    let mut gz = flate2::write::GzEncoder::new(std::fs::File::create(&gz_path).unwrap(), flate2::Compression::fast());
    gz.write_all(&std::fs::read(&tar_path).unwrap()).unwrap();
    gz.finish().unwrap();
    let from_tar = open(&tar_path).unwrap().read_frame(2, 7).unwrap();
    let bundle = open(&gz_path).unwrap();
    assert_eq!(bundle.views.len(), 3);
    assert_eq!(bundle.read_frame(2, 7).unwrap(), from_tar);
    // Held to the same caps as any archive.
    let caps = Limits { max_total_bytes: 1_000_000, ..Limits::default() };
    expect_error(open_with(&gz_path, caps), "bundle_too_large", &[]);
    // A gzip of something else.
    let not_tar = out.path().join("x.gz");
    let mut gz = flate2::write::GzEncoder::new(std::fs::File::create(&not_tar).unwrap(), flate2::Compression::fast());
    gz.write_all(&[b'x'; 4096]).unwrap();
    gz.finish().unwrap();
    expect_error(open(&not_tar), "invalid_archive", &["holds no tar"]);

    // Two folders deep, as `tar -cf x.tar out/ci` makes it.
    let deep = out.path().join("deep.tar");
    tar_dir(s.path(), &deep, Some("out/ci"));
    let message = expect_error(open(&deep), "missing_file", &["out/ci/manifest.json", "tar -C out/ci"]);
    assert!(message.contains("-cf bundle.tar ."), "{message}");
}

/// Issue 49: a misspelt manifest key is refused naming the key meant; a field this reader does not
/// know and that spells no known one is read past and listed (the contract lets new optional
/// fields appear).
#[test]
fn a_misspelt_key_is_named_with_the_key_meant() {
    let s = Scratch::new();
    s.edit(|m| {
        let serial = m["part"]["serial"].take();
        m["part"].as_object_mut().unwrap().remove("serial");
        m["part"]["serail"] = serial;
    });
    expect_error(open(s.path()), "invalid_manifest", &["part.serail", "did you mean `part.serial`"]);
    let s = Scratch::new();
    s.edit(|m| {
        let format = m["format"].take();
        m.as_object_mut().unwrap().remove("format");
        m["fromat"] = format;
    });
    expect_error(open(s.path()), "invalid_manifest", &["fromat", "did you mean `format`"]);
    let s = Scratch::new();
    s.edit(|m| m["fixture"] = json!({"line": 3}));
    let bundle = open(s.path()).unwrap();
    assert_eq!(bundle.unread_fields, ["fixture"]);
}

#[test]
fn archive_bombs_hit_the_caps() {
    let s = Scratch::new();
    let out = tempfile::tempdir().unwrap();
    let zip_path = out.path().join("b.zip");
    zip_dir(s.path(), &zip_path, None);
    let caps = Limits { max_total_bytes: 1_000_000, ..Limits::default() };
    expect_error(open_with(&zip_path, caps), "bundle_too_large", &["1000000"]);
    let caps = Limits { max_files: 10, ..Limits::default() };
    expect_error(open_with(&zip_path, caps), "bundle_too_large", &["10 files"]);
    // A highly compressible entry that inflates past the per-file cap.
    let bomb = out.path().join("bomb.zip");
    let mut zip = zip::ZipWriter::new(std::fs::File::create(&bomb).unwrap());
    let options = zip::write::SimpleFileOptions::default().compression_method(zip::CompressionMethod::Deflated);
    zip.start_file("manifest.json", options).unwrap();
    zip.write_all(&vec![b' '; 3_000_000]).unwrap();
    zip.finish().unwrap();
    assert!(std::fs::metadata(&bomb).unwrap().len() < 100_000);
    let caps = Limits { max_file_bytes: 1_000_000, ..Limits::default() };
    expect_error(open_with(&bomb, caps), "bundle_too_large", &["manifest.json"]);
    // The same caps hold for a directory.
    let caps = Limits { max_files: 10, ..Limits::default() };
    expect_error(open_with(s.path(), caps), "bundle_too_large", &["10 files"]);
}

#[test]
fn tar_links_are_refused() {
    let s = Scratch::new();
    let out = tempfile::tempdir().unwrap();
    let tar_path = out.path().join("link.tar");
    let mut builder = tar::Builder::new(std::fs::File::create(&tar_path).unwrap());
    builder.append_path_with_name(s.path().join("manifest.json"), "manifest.json").unwrap();
    let mut header = tar::Header::new_gnu();
    header.set_entry_type(tar::EntryType::Symlink);
    header.set_size(0);
    builder.append_link(&mut header, "a000-z00/000.png", "/etc/passwd").unwrap();
    builder.finish().unwrap();
    expect_error(open(&tar_path), "unsafe_path", &["a000-z00/000.png", "link"]);
}

#[test]
fn gray_rgb_png_and_tiff_in_8_and_16_bits() {
    let s = Scratch::new();
    let m = s.manifest();
    let formats = [("png", false, true), ("png", true, true), ("tif", true, false), ("tiff", false, false)];
    let mut manifest = m.clone();
    for (v, (ext, sixteen, gray)) in formats.iter().enumerate().take(3) {
        let frames = manifest["views"][v]["frames"].as_array_mut().unwrap();
        for (k, frame) in frames.iter_mut().enumerate() {
            let name = format!("custom{v}/{k:03}.{ext}");
            std::fs::create_dir_all(s.path().join(format!("custom{v}"))).unwrap();
            write_png(&s.path().join(&name), 64, 48, *sixteen, *gray);
            frame["file"] = json!(name);
        }
    }
    s.set_manifest(&manifest);
    let bundle = open(s.path()).unwrap();
    let f0 = bundle.read_frame(0, 1).unwrap();
    assert_eq!((f0.channels, f0.width), (1, 64));
    assert_eq!(f0.samples.value(5), 5.0 / 255.0);
    let f1 = bundle.read_frame(1, 1).unwrap();
    assert_eq!(bundle.views[1].format.bit_depth, 16);
    assert_eq!(f1.samples.value(3), (3 * 97) as f32 / 65535.0);
    let f2 = bundle.read_frame(2, 0).unwrap();
    assert_eq!((f2.channels, bundle.views[2].format.bit_depth), (3, 16));
    // Other colour types are refused by name.
    let name = manifest["views"][0]["frames"][0]["file"].as_str().unwrap().to_string();
    image::RgbaImage::new(64, 48).save(s.path().join(&name)).unwrap();
    expect_error(open(s.path()), "unreadable_frame", &[&name, "gray or RGB"]);
}

/// A zip entry whose bytes no longer match its CRC, and a tar cut inside an entry, are the
/// client's damaged archive (`invalid_archive`, naming the file), not a server I/O failure.
#[test]
fn damaged_archive_entries_are_the_clients_error() {
    let s = Scratch::new();
    let out = tempfile::tempdir().unwrap();
    let file = s.manifest()["views"][2]["frames"][7]["file"].as_str().unwrap().to_string();
    let frame_bytes = std::fs::read(s.path().join(&file)).unwrap();
    // A run of bytes from the middle of the frame (past the PNG headers) locates it in the archive.
    let probe = &frame_bytes[frame_bytes.len() / 2..frame_bytes.len() / 2 + 64];
    let find =
        |haystack: &[u8]| haystack.windows(probe.len()).position(|w| w == probe).expect("frame bytes in the archive");

    let zip_path = out.path().join("b.zip");
    zip_dir(s.path(), &zip_path, None);
    let mut bytes = std::fs::read(&zip_path).unwrap();
    let at = find(&bytes);
    bytes[at + 10] ^= 0x5a;
    std::fs::write(&zip_path, &bytes).unwrap();
    // Opening reads every frame (whatever the frame check), so the damage is found there, named.
    expect_error(open(&zip_path), "invalid_archive", &[&file, "damaged"]);
    expect_error(open_with(&zip_path, Limits::default()), "invalid_archive", &[&file, "damaged"]);

    let tar_path = out.path().join("b.tar");
    tar_dir(s.path(), &tar_path, None);
    let bytes = std::fs::read(&tar_path).unwrap();
    let cut = find(&bytes);
    let short = out.path().join("short.tar");
    std::fs::write(&short, &bytes[..cut]).unwrap();
    // Indexing skips over the cut frame's data and runs out: the message names that frame.
    expect_error(open(&short), "invalid_archive", &[&file, "damaged", "ends inside"]);
}

/// A station the method cannot measure at is refused before any work, naming the parameter: a
/// pixel too coarse for the pitch or beyond the coarsest station class, frames too far apart for a focus curve, a stack too short for
/// the thread's depth. (The ci bundle: 41 µm pixels, frames every 0.25 mm, 18 of them; BC 4-1/2,
/// 5.08 mm pitch, 1.575 mm deep.)
#[test]
fn a_station_the_method_cannot_measure_at_is_refused_naming_its_parameter() {
    let bundle_error = |s: &Scratch| {
        let err = open(s.path()).expect_err("the station should be refused");
        assert_eq!(err.code().name(), "station_out_of_range", "{err}");
        (err.culprit().unwrap(), err.to_string())
    };
    // Pixels 14 times as large on the sensor: 0.57 mm on the part, fewer than 10 a pitch.
    let coarse = Scratch::new();
    coarse.edit(|m| m["optics"]["pixel_pitch_um"] = json!(12.0 * 14.0));
    let (culprit, message) = bundle_error(&coarse);
    assert_eq!(culprit, "manifest.json: optics.pixel_pitch_um");
    assert!(message.contains("5.08 mm pitch needs at least 10 pixels"), "{message}");
    // Pixels 4.5 times as large: 0.184 mm, 28 a pitch, but coarser than any station class the
    // station benchmark measured (up to 0.15 mm).
    let beyond = Scratch::new();
    beyond.edit(|m| m["optics"]["pixel_pitch_um"] = json!(12.0 * 4.5));
    let (culprit, message) = bundle_error(&beyond);
    assert_eq!(culprit, "manifest.json: optics.pixel_pitch_um");
    assert!(message.contains("covers 0.184 mm") && message.contains("coarsest station class"), "{message}");
    // 3.5 times (0.143 mm): the coarse class, opened.
    let coarse_class = Scratch::new();
    coarse_class.edit(|m| m["optics"]["pixel_pitch_um"] = json!(12.0 * 3.5));
    assert!(open(coarse_class.path()).is_ok());
    // Frames ten times as far apart: 2.5 mm, five depths of field.
    let sparse = Scratch::new();
    sparse.edit(|m| {
        for frame in m["views"][1]["frames"].as_array_mut().unwrap() {
            frame["offset_mm"] = json!(10.0 * frame["offset_mm"].as_f64().unwrap());
        }
    });
    let (culprit, message) = bundle_error(&sparse);
    assert_eq!(culprit, "manifest.json: views[1].frames");
    assert!(message.contains("depths of field") && message.contains("at most 2"), "{message}");
    // Four frames 0.25 mm apart span 0.75 mm of a 1.575 mm deep thread.
    let short = Scratch::new();
    short.edit(|m| m["views"][2]["frames"].as_array_mut().unwrap().truncate(4));
    let (culprit, message) = bundle_error(&short);
    assert_eq!(culprit, "manifest.json: views[2].frames");
    assert!(message.contains("spans 0.750 mm") && message.contains("1.575 mm deep"), "{message}");
    // The same bundle as it is opens.
    assert!(open(Scratch::new().path()).is_ok());
}

/// Issue 49: a command's error is its message and causes; a `RUST_BACKTRACE` set for other
/// programs adds no frames, and `CRESTSCAN_BACKTRACE=1` asks for them.
#[test]
fn cli_errors_carry_a_backtrace_only_when_asked() {
    let missing = tempfile::tempdir().unwrap().path().join("nowhere.tar");
    let run = |var: &str| {
        std::process::Command::new(env!("CARGO_BIN_EXE_crestscan"))
            .args(["validate", missing.to_str().unwrap()])
            .env_remove("RUST_BACKTRACE")
            .env_remove("CRESTSCAN_BACKTRACE")
            .env(var, "1")
            .output()
            .unwrap()
    };
    let plain = run("RUST_BACKTRACE");
    assert!(!plain.status.success());
    let text = String::from_utf8_lossy(&plain.stderr).into_owned();
    assert!(text.starts_with("Error: ") && text.contains("nowhere.tar"), "{text}");
    assert!(text.lines().count() <= 4, "a {} line error:\n{text}", text.lines().count());
    let asked = run("CRESTSCAN_BACKTRACE");
    let traced = String::from_utf8_lossy(&asked.stderr).into_owned();
    assert!(traced.starts_with(&text) && traced.lines().count() > text.lines().count() + 3, "{traced}");
}
