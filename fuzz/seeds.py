#!/usr/bin/env python3
"""Writes the fuzz targets' seed corpus (fuzz/corpus/<target>/seed-*): small valid inputs whose
structure the fuzzer mutates. Deterministic; run by scripts/fuzz when a corpus folder is missing."""
import io, json, os, struct, sys, tarfile, zipfile, zlib

root = os.path.join(os.path.dirname(os.path.abspath(__file__)), "corpus")


def png(width, height, level):
    def chunk(kind, data):
        body = kind + data
        return struct.pack(">I", len(data)) + body + struct.pack(">I", zlib.crc32(body))
    rows = b"".join(b"\0" + bytes((level + x * 7 + y * 3) & 255 for x in range(width)) for y in range(height))
    ihdr = struct.pack(">IIBBBBB", width, height, 8, 0, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", ihdr) + chunk(b"IDAT", zlib.compress(rows)) + chunk(b"IEND", b"")


def manifest(views, frames):
    return {
        "format": "crestscan.focal-stack/1",
        "part": {"serial": "FUZZ-1", "connection": "BC 4-1/2", "thread": None},
        "optics": {"projection": "perspective", "focal_length_mm": 50.0, "f_number": 2.8,
                   "focus_distance_mm": 120.0, "pixel_pitch_um": 3.45, "principal_point_px": None,
                   "magnification": None},
        "views": [{"id": f"v{v}", "pose": {"angle_deg": 5.0 * v, "axial_mm": 12.0, "lens_radius_mm": 177.2},
                   "frames": [{"file": f"v{v}/{k:03}.png", "offset_mm": -0.5 + 0.25 * k} for k in range(frames)]}
                  for v in range(views)],
    }


def files(views=2, frames=3):
    m = manifest(views, frames)
    out = [("manifest.json", json.dumps(m, indent=1).encode())]
    for view in m["views"]:
        for k, frame in enumerate(view["frames"]):
            out.append((frame["file"], png(16, 8, 40 * k)))
    return out


def write(target, name, data):
    os.makedirs(os.path.join(root, target), exist_ok=True)
    with open(os.path.join(root, target, name), "wb") as f:
        f.write(data)


def tar_bytes(entries):
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w", format=tarfile.USTAR_FORMAT) as tar:
        for name, data in entries:
            info = tarfile.TarInfo(name)
            info.size, info.mtime, info.mode = len(data), 0, 0o644
            tar.addfile(info, io.BytesIO(data))
    return buf.getvalue()


def zip_bytes(entries, method):
    buf = io.BytesIO()
    with zipfile.ZipFile(buf, "w", method) as z:
        for name, data in entries:
            z.writestr(zipfile.ZipInfo(name, (1980, 1, 1, 0, 0, 0)), data, compress_type=method)
    return buf.getvalue()


def main():
    entries = files()
    write("manifest", "seed-small", entries[0][1])
    write("manifest", "seed-custom-thread", json.dumps({**manifest(1, 3), "part": {"thread": {
        "family": "buttress", "pitch_mm": 5.08, "thread_height_mm": 1.575, "height_tolerance_mm": 0.025,
        "taper_on_diameter": 0.0625, "pipe_od_mm": 114.3, "lc_mm": 35.8}}}).encode())
    write("bundle", "seed-tar", tar_bytes(entries))
    write("bundle", "seed-zip-deflated", zip_bytes(entries, zipfile.ZIP_DEFLATED))
    write("bundle", "seed-zip-stored", zip_bytes(files(1, 3), zipfile.ZIP_STORED))
    write("cmm", "seed-csv", b"thread,angle_deg,height_mm\n1,0.5,1.574\n1,,1.575\n3,90.0,0.9826\n")
    write("cmm", "seed-json", json.dumps({"points": [{"thread": 1, "angle_deg": 0.5, "height_mm": 1.574},
                                                     {"thread": 2, "height_mm": 1.57}]}).encode())


if __name__ == "__main__":
    sys.exit(main())
