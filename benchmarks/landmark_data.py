"""Two public landmark datasets, taken out of local git mirrors, for a landmark-transfer benchmark.

``femur`` and ``pelvis``: VSDFullBodyBoneModels (github.com/RWTHmediTEC/VSDFullBodyBoneModels,
commit ee5c4f0 = release v2.0, Fischer et al., Sci. Rep. 9:13322 (2019) and 10:20859 (2020)),
licence CC BY-NC-SA: use for benchmarks only, never commit the data. ``Bones/zNNN.mat`` holds a
struct array ``B`` (fields ``name``, ``date``, ``mesh`` with ``vertices`` in mm and 1-based
``faces``) for Sacrum, Hip_R, Hip_L, Femur_R, Femur_L; ``ManualLandmarks/<Bone>/RaterN.mat``
holds a cell array ``Results``: one row per subject, four columns of trials (each a cell of
``{name, [x y z], vertex index}`` per landmark), then the subject id and, for the femur, the side
that was landmarked (L and R alternate). Five raters, four trials each, 22 femoral and 14 pelvic
landmarks. Subject z024 is a duplicate of z013 (same bones, slightly different segmentation;
removed upstream in v3.0): it is left out unless ``--keep-duplicate``. The femurs mix sides, so right ones are mirrored (x -> -x, face
orientation flipped) to look like left ones, unless ``--no-mirror``; the pelvis is the three
bones (sacrum, right and left hip) in one mesh of three closed pieces, with a cell array ``bone``.

``vertebrae``: the L1 vertebrae (VerSe 2020 label 20) of how-to-shape-model
(github.com/madsendennis/how-to-shape-model, HEAD; Apache-2.0 repository, VerSe data CC BY-SA),
``data/vertebrae/raw/*.ply`` with a Scalismo landmark JSON next to each (ids A..J, one rater, one
trial), plus the reference ``ref_20`` in its own frame. A vertebra or femur mesh keeps only its
largest connected piece (sub-verse010 has a 24-face speck besides the bone).

For each dataset it writes ``DIR/<dataset>/meshes/<case>.vtp`` (merged vertices, triangles only),
``landmarks/<case>.csv`` (``label,x,y,z``, the mean over raters and trials, the mesh's frame),
``raters.json`` (each rater's trials per case and label, and the raters' spread) and
``summary.json`` (mesh checks), and prints the checks and the spread:

    python benchmarks/landmark_data.py --output /tmp/landmarks
"""

from __future__ import annotations

import argparse
import csv
import io
import json
import re
import subprocess
import tempfile
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import scipy.io
import vtk
from vtk.util.numpy_support import numpy_to_vtk, numpy_to_vtkIdTypeArray, vtk_to_numpy

MIRRORS = "/work/.mirror"  # where the search tool's fetch puts github:owner/name
VSD_DUPLICATES = ("z024",)
PELVIS_BONES = ("Sacrum", "Hip_R", "Hip_L")  # the order the raters' vertex indices assume


# ---------------------------------------------------------------- git


@dataclass(frozen=True)
class Source:
    """A public git repository the data is read from, at a fixed commit."""

    repository: str  # owner/name on GitHub
    commit: str
    licence: str

    def git_dir(self, mirrors: str) -> str:
        """The bare git directory of the local mirror (``<mirrors>/<owner>+<name>/repo``)."""
        path = Path(mirrors) / self.repository.replace("/", "+") / "repo"
        if not path.is_dir():
            raise SystemExit(f"no mirror of {self.repository} at {path} (fetch "
                             f"github:{self.repository}, or pass --mirrors)")
        return str(path)


VSD = Source("RWTHmediTEC/VSDFullBodyBoneModels", "ee5c4f0", "CC BY-NC-SA 4.0")
VERSE = Source("madsendennis/how-to-shape-model", "HEAD", "Apache-2.0 (VerSe data CC BY-SA 4.0)")


def git_show(git_dir: str, commit: str, path: str) -> bytes:
    """The bytes of ``path`` at ``commit`` in a bare git directory."""
    return subprocess.run(["git", "--git-dir", git_dir, "show", f"{commit}:{path}"],
                          capture_output=True, check=True).stdout


def git_list(git_dir: str, commit: str, folder: str) -> list[str]:
    """The file paths under ``folder`` at ``commit``."""
    out = subprocess.run(["git", "--git-dir", git_dir, "ls-tree", "-r", "--name-only", commit,
                          folder], capture_output=True, check=True, text=True).stdout
    return sorted(out.split())


def git_commit(git_dir: str, commit: str) -> str:
    """The full hash of ``commit``."""
    return subprocess.run(["git", "--git-dir", git_dir, "rev-parse", commit],
                          capture_output=True, check=True, text=True).stdout.strip()


# ---------------------------------------------------------------- meshes


def to_polydata(vertices: np.ndarray, faces: np.ndarray, bone: np.ndarray | None = None):
    """vtkPolyData of triangles (0-based ``faces``); ``bone`` an optional per-face id array."""
    points = vtk.vtkPoints()
    points.SetData(numpy_to_vtk(np.ascontiguousarray(vertices, dtype=np.float64), deep=True))
    cells = vtk.vtkCellArray()
    offsets = numpy_to_vtkIdTypeArray(np.arange(0, 3 * len(faces) + 1, 3, dtype=np.int64), deep=True)
    conn = numpy_to_vtkIdTypeArray(np.ascontiguousarray(faces, dtype=np.int64).ravel(), deep=True)
    cells.SetData(offsets, conn)
    poly = vtk.vtkPolyData()
    poly.SetPoints(points)
    poly.SetPolys(cells)
    if bone is not None:
        array = numpy_to_vtk(np.ascontiguousarray(bone, dtype=np.int32), deep=True)
        array.SetName("bone")
        poly.GetCellData().AddArray(array)
    return poly


def clean(poly):
    """Coincident vertices merged, degenerate and non-triangle cells dropped, unused points removed."""
    merge = vtk.vtkCleanPolyData()
    merge.SetInputData(poly)
    merge.SetTolerance(0.0)
    triangles = vtk.vtkTriangleFilter()  # collapsed faces became lines or vertices: drop them
    triangles.SetInputConnection(merge.GetOutputPort())
    triangles.PassLinesOff()
    triangles.PassVertsOff()
    return without_unused_points(triangles.GetOutputPort())


def largest_piece(poly):
    """The largest connected piece, unused points removed."""
    pieces = vtk.vtkPolyDataConnectivityFilter()
    pieces.SetInputData(poly)
    pieces.SetExtractionModeToLargestRegion()
    return without_unused_points(pieces.GetOutputPort())


def without_unused_points(port):
    """A copy of the polydata of a pipeline's output ``port``, points in no cell removed."""
    unused = vtk.vtkCleanPolyData()
    unused.SetInputConnection(port)
    unused.SetTolerance(0.0)
    unused.Update()
    out = vtk.vtkPolyData()
    out.DeepCopy(unused.GetOutput())
    return out


def mirror_x(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """x -> -x, with each face's vertex order reversed so the normals still point outwards."""
    vertices = vertices.copy()
    vertices[:, 0] *= -1.0
    return vertices, faces[:, ::-1].copy()


def triangles_of(poly) -> np.ndarray:
    """The (F, 3) vertex indices of a triangles-only vtkPolyData."""
    return vtk_to_numpy(poly.GetPolys().GetConnectivityArray()).reshape(-1, 3)


def mesh_checks(poly) -> dict:
    """Vertices, faces, edges, open edges, Euler characteristic, pieces, box size, volume."""
    faces = triangles_of(poly)
    vertices = vtk_to_numpy(poly.GetPoints().GetData())
    edges = np.sort(faces[:, [0, 1, 1, 2, 2, 0]].reshape(-1, 2), axis=1)
    n_edges = len(np.unique(edges, axis=0))
    features = vtk.vtkFeatureEdges()
    features.SetInputData(poly)
    features.BoundaryEdgesOn()
    features.NonManifoldEdgesOn()
    features.FeatureEdgesOff()
    features.ManifoldEdgesOff()
    features.Update()
    open_edges = features.GetOutput().GetNumberOfLines()
    pieces = vtk.vtkPolyDataConnectivityFilter()
    pieces.SetInputData(poly)
    pieces.SetExtractionModeToAllRegions()
    pieces.Update()
    a, b, c = (vertices[faces[:, k]] for k in range(3))
    volume = float(np.einsum("ij,ij->i", a, np.cross(b, c)).sum() / 6.0)
    euler = len(vertices) - n_edges + len(faces)
    return {"vertices": len(vertices), "faces": len(faces), "edges": n_edges,
            "open_edges": int(open_edges), "closed": open_edges == 0, "euler": int(euler),
            "pieces": pieces.GetNumberOfExtractedRegions(),
            "box_mm": [round(float(s), 1) for s in np.ptp(vertices, axis=0)],
            "volume_ml": round(volume / 1000.0, 2)}


def surface_distances(poly, points: np.ndarray) -> np.ndarray:
    """Distance of each point to the closest point of the surface."""
    locator = vtk.vtkCellLocator()
    locator.SetDataSet(poly)
    locator.BuildLocator()
    closest, cell, sub, d2 = [0.0, 0.0, 0.0], vtk.reference(0), vtk.reference(0), vtk.reference(0.0)
    out = []
    for p in np.asarray(points, dtype=float).reshape(-1, 3):
        locator.FindClosestPoint(p.tolist(), closest, cell, sub, d2)
        out.append(np.sqrt(float(d2)))
    return np.array(out)


def write_vtp(poly, path: Path) -> None:
    """An XML PolyData file (binary, compressed)."""
    writer = vtk.vtkXMLPolyDataWriter()
    writer.SetFileName(str(path))
    writer.SetInputData(poly)
    writer.SetDataModeToBinary()
    if not writer.Write():
        raise OSError(f"could not write {path}")


def read_vtp(path: Path):
    """Read an XML PolyData file back."""
    reader = vtk.vtkXMLPolyDataReader()
    reader.SetFileName(str(path))
    reader.Update()
    return reader.GetOutput()


# ---------------------------------------------------------------- landmarks


def short_label(name: str) -> str:
    """'Superior Femoral Head (SFH)' -> 'SFH', 'Left Pubic Tubercle (PT)' -> 'PT_L',
    'Right ASIS' -> 'ASIS_R'."""
    side = ""
    match = re.match(r"(Left|Right) (.*)", name)
    if match:
        side, name = "_" + match.group(1)[0], match.group(2)
    abbreviation = re.search(r"\(([^)]+)\)\s*$", name)
    core = abbreviation.group(1) if abbreviation else re.sub(r"\W+", "_", name).strip("_")
    return core + side


def write_landmarks_csv(path: Path, labels: list[str], points: np.ndarray) -> None:
    """``label,x,y,z``, one row per landmark."""
    with open(path, "w", newline="") as handle:
        writer = csv.writer(handle)
        writer.writerow(["label", "x", "y", "z"])
        for label, p in zip(labels, points):
            writer.writerow([label] + [f"{float(v):.4f}" for v in p])


def rater_spread(points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """From (raters, trials, landmarks, 3): the inter-rater spread, per landmark the mean over
    raters of the distance from the rater's mean (over trials) to the mean of the other raters;
    and the intra-rater spread, the mean distance of each trial to its rater's mean."""
    per_rater = points.mean(axis=1)
    n = len(per_rater)
    others = (per_rater.sum(axis=0)[None] - per_rater) / max(n - 1, 1)
    inter = np.linalg.norm(per_rater - others, axis=-1).mean(axis=0)
    intra = np.linalg.norm(points - per_rater[:, None], axis=-1).mean(axis=(0, 1))
    return inter, intra


def spread_summary(labels: list[str], values: np.ndarray) -> dict:
    """Median and mean (mm) per label over cases, and over all cases and labels; values (cases,
    labels)."""
    summary = {label: {"median": round(float(np.median(values[:, k])), 3),
                       "mean": round(float(values[:, k].mean()), 3)}
               for k, label in enumerate(labels)}
    summary["overall"] = {"median": round(float(np.median(values)), 3),
                          "mean": round(float(values.mean()), 3)}
    return summary


def femur_side_from_anatomy(labels: list[str], points: np.ndarray) -> str:
    """'L' or 'R' from the handedness of medial, anterior and superior directions
    (epicondyles, femoral head front/back, head top/notch); in a right-handed frame
    medial x anterior points superior for a left femur."""
    p = dict(zip(labels, points))
    medial = p["MEC"] - p["LEC"]
    anterior = p["AFH"] - p["PFH"]
    superior = p["SFH"] - p["ICN"]
    return "L" if np.dot(np.cross(medial, anterior), superior) > 0 else "R"


# ---------------------------------------------------------------- datasets


def load_mat(git_dir: str, commit: str, path: str) -> dict:
    """A MATLAB v5 MAT file out of git."""
    return scipy.io.loadmat(io.BytesIO(git_show(git_dir, commit, path)))


def vsd_raters(git: str, bone: str) -> tuple[list[str], dict, list[str]]:
    """Rater names; per subject (side, points (raters, trials, landmarks, 3)); landmark names."""
    files = [f for f in git_list(git, VSD.commit, f"ManualLandmarks/{bone}")
             if f.endswith(".mat")]
    raters, subjects, names = [], {}, None
    for r, path in enumerate(files):
        results = load_mat(git, VSD.commit, path)["Results"]
        raters.append(Path(path).stem)
        trials = [j for j in range(results.shape[1]) if results[0, j].dtype == object]
        for row in results:
            subject = str(row[trials[-1] + 1].item())
            side = str(row[trials[-1] + 2].item()) if results.shape[1] > trials[-1] + 2 else ""
            this = [[str(c[0].item()) for c in row[t]] for t in trials]
            names = names or this[0]
            if any(n != names for n in this):
                raise ValueError(f"{path} {subject}: landmark names differ")
            pts = np.array([[np.asarray(c[1], float).reshape(3) for c in row[t]]
                            for t in trials])
            entry = subjects.setdefault(subject, {"side": side, "points": [None] * len(files)})
            if entry["side"] != side:
                raise ValueError(f"{path} {subject}: side {side} != {entry['side']}")
            entry["points"][r] = pts
    for subject, entry in subjects.items():
        entry["points"] = np.stack(entry["points"])  # fails if a rater lacks a subject
    return raters, subjects, names


def vsd_bones(git: str, subject: str) -> dict:
    """Bone name -> (vertices (V, 3) mm, faces (F, 3) 0-based) of one subject."""
    bones = {}
    for b in load_mat(git, VSD.commit, f"Bones/{subject}.mat")["B"].ravel():
        mesh = b["mesh"]
        if mesh.size == 0:
            continue
        mesh = mesh[0, 0]
        faces = np.asarray(mesh["faces"], dtype=np.int64) - 1
        bones[str(b["name"].item())] = (np.asarray(mesh["vertices"], dtype=np.float64), faces)
    return bones


def vsd_cases(git: str, bone: str, mirror: bool, keep_duplicate: bool):
    """Yield (case, vertices, faces, bone ids or None, names, points, info) for femur or pelvis."""
    raters, subjects, names = vsd_raters(git, bone.capitalize())
    sides = {e["side"] for e in subjects.values()}
    mirror = mirror and bone == "femur" and len(sides) > 1
    for subject in sorted(subjects):
        if subject in VSD_DUPLICATES and not keep_duplicate:
            print(f"  {subject}: left out (duplicate of z013, removed upstream in v3.0)")
            continue
        if not re.fullmatch(r"z\d{3}", subject):  # e.g. the phantom of later versions
            print(f"  {subject}: left out (not a VSD subject)")
            continue
        entry, bones = subjects[subject], vsd_bones(git, subject)
        points, info = entry["points"], {"subject": subject, "raters": raters}
        if bone == "femur":
            side = entry["side"]
            vertices, faces = bones[f"Femur_{side}"]
            ids = None
            labels = [short_label(n) for n in names]
            info.update(side=side, side_from_anatomy=femur_side_from_anatomy(
                labels, points.mean(axis=(0, 1))), mirrored=bool(mirror and side == "R"))
            case = f"{subject}_femur_{side}" if len(sides) > 1 else f"{subject}_femur"
            if info["mirrored"]:
                vertices, faces = mirror_x(vertices, faces)
                points = points * np.array([-1.0, 1.0, 1.0])
        else:
            parts = [bones[b] for b in PELVIS_BONES]
            starts = np.cumsum([0] + [len(v) for v, _ in parts])
            vertices = np.concatenate([v for v, _ in parts])
            faces = np.concatenate([f + s for (_, f), s in zip(parts, starts)])
            ids = np.concatenate([np.full(len(f), k) for k, (_, f) in enumerate(parts)])
            info.update(side="both", mirrored=False, bone_ids=dict(enumerate(PELVIS_BONES)))
            case = f"{subject}_pelvis"
        yield case, vertices, faces, ids, names, points, info


def read_ply(data: bytes):
    """vtkPolyData from PLY bytes (through a temporary file)."""
    with tempfile.NamedTemporaryFile(suffix=".ply") as tmp:
        tmp.write(data)
        tmp.flush()
        reader = vtk.vtkPLYReader()
        reader.SetFileName(tmp.name)
        reader.Update()
        poly = vtk.vtkPolyData()
        poly.DeepCopy(reader.GetOutput())
    return poly


def ply_space(data: bytes) -> str:
    """The ``comment SPACE=...`` of a PLY header, or '?'."""
    header = data[: data.find(b"end_header")].decode("ascii", "replace")
    match = re.search(r"comment SPACE=(\w+)", header)
    return match.group(1) if match else "?"


def vertebra_cases(git: str):
    """Yield (case, vertices, faces, None, names, points, info) for the L1 vertebrae."""
    paths = [p for p in git_list(git, VERSE.commit, "data/vertebrae") if p.endswith(".ply")]
    for path in paths:
        data = git_show(git, VERSE.commit, path)
        poly = read_ply(data)
        landmarks = json.loads(git_show(git, VERSE.commit, path[:-4] + ".json"))
        names = [lm["id"] for lm in landmarks]
        points = np.array([[[lm["coordinates"] for lm in landmarks]]], dtype=float)
        vertices = vtk_to_numpy(poly.GetPoints().GetData()).astype(np.float64)
        cells = poly.GetPolys()
        sizes = np.diff(vtk_to_numpy(cells.GetOffsetsArray()))
        if np.any(sizes != 3):
            raise ValueError(f"{path}: faces that are not triangles")
        faces = vtk_to_numpy(cells.GetConnectivityArray()).reshape(-1, 3).astype(np.int64)
        stem = Path(path).stem
        case = stem.replace("_segment_20", "")
        info = {"source": path, "space": ply_space(data), "side": "midline", "mirrored": False,
                "raters": ["annotator"]}
        yield case, vertices, faces, None, names, points, info


# ---------------------------------------------------------------- driver


def export(dataset: str, cases, output: Path) -> dict:
    """Write meshes, landmark CSVs, raters.json and summary.json of one dataset; print checks."""
    root = output / dataset
    (root / "meshes").mkdir(parents=True, exist_ok=True)
    (root / "landmarks").mkdir(parents=True, exist_ok=True)
    raters_json = {"dataset": dataset, "units": "mm", "cases": {}}
    summary, inter_all, intra_all, labels = {}, [], [], None
    print(f"\n== {dataset}")
    print(f"  {'case':24s} {'V':>6s} {'F':>6s} closed euler pieces {'box mm':>22s} "
          f"{'vol ml':>7s} LMs  NaN  dist raters/mean mm  side")
    for case, vertices, faces, ids, names, points, info in cases:
        labels = [short_label(n) for n in names]
        if labels != list(dict.fromkeys(labels)):
            raise ValueError(f"{case}: repeated landmark labels {labels}")
        poly = clean(to_polydata(vertices, faces, ids))
        dropped = 0
        if dataset != "pelvis":
            whole = poly.GetNumberOfPoints()
            poly = largest_piece(poly)
            dropped = whole - poly.GetNumberOfPoints()
        checks = mesh_checks(poly)
        nan = int(np.isnan(points).any(axis=-1).sum())
        mean = np.nanmean(points, axis=(0, 1))
        d_raters = surface_distances(poly, points[~np.isnan(points).any(axis=-1)])
        d_mean = surface_distances(poly, mean)
        write_vtp(poly, root / "meshes" / f"{case}.vtp")
        write_landmarks_csv(root / "landmarks" / f"{case}.csv", labels, mean)
        checks.update(landmarks=len(labels), nan_points=nan, vertices_of_other_pieces=dropped,
                      rater_points_to_surface_max_mm=round(float(d_raters.max()), 3),
                      mean_to_surface_max_mm=round(float(d_mean.max()), 3))
        summary[case] = {**{k: v for k, v in info.items() if k != "raters"}, **checks}
        raters_json["cases"][case] = {
            "side": info.get("side"), "mirrored": info.get("mirrored", False),
            "raters": info["raters"],
            "points": {lab: np.round(points[:, :, k], 4).tolist() for k, lab in enumerate(labels)}}
        raters_json["labels"] = dict(zip(labels, names))
        if points.shape[0] > 1:
            inter, intra = rater_spread(points)
            inter_all.append(inter)
            intra_all.append(intra)
        side = info.get("side", "")
        if "side_from_anatomy" in info:
            side += f" (anatomy {info['side_from_anatomy']})"
        if info.get("mirrored"):
            side += " mirrored"
        if dropped:
            side += f"; {dropped} vertices of smaller pieces dropped"
        print(f"  {case:24s} {checks['vertices']:6d} {checks['faces']:6d} "
              f"{'yes' if checks['closed'] else 'NO ':>6s} {checks['euler']:5d} "
              f"{checks['pieces']:6d} {'x'.join(f'{s:.0f}' for s in checks['box_mm']):>22s} "
              f"{checks['volume_ml']:7.1f} {len(labels):3d} {nan:4d} "
              f"{d_raters.max():8.3f} {d_mean.max():6.3f}  {side}")
    raters_json["layout"] = "points[label] = [rater][trial] -> [x, y, z], mm, the mesh's frame"
    if inter_all:
        inter_s = spread_summary(labels, np.array(inter_all))
        intra_s = spread_summary(labels, np.array(intra_all))
        raters_json["spread"] = {
            "inter_rater": inter_s, "intra_rater": intra_s,
            "definition": "inter: mean over raters of |rater mean over trials - mean of the other "
                          "raters|; intra: mean |trial - its rater's mean|; median and mean over "
                          "cases (mm)"}
        print("  raters' spread, mm (median / mean over cases): inter-rater | intra-rater")
        for label in labels + ["overall"]:
            a, b = inter_s[label], intra_s[label]
            print(f"    {label:8s} {a['median']:6.2f} / {a['mean']:6.2f} | "
                  f"{b['median']:6.2f} / {b['mean']:6.2f}")
    else:
        print("  raters' spread: not available (one rater, one trial)")
    (root / "raters.json").write_text(json.dumps(raters_json, indent=1))
    (root / "summary.json").write_text(json.dumps(summary, indent=1))
    return summary


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--output", required=True, help="work folder (never commit its content)")
    parser.add_argument("--datasets", nargs="+", default=["femur", "pelvis", "vertebrae"],
                        choices=["femur", "pelvis", "vertebrae"])
    parser.add_argument("--no-mirror", action="store_true",
                        help="keep right femurs as they are instead of mirroring them")
    parser.add_argument("--keep-duplicate", action="store_true",
                        help="keep VSD subject z024, a duplicate removed upstream in v3.0")
    parser.add_argument("--mirrors", default=MIRRORS,
                        help="folder of the git mirrors, <owner>+<name>/repo (default %(default)s)")
    args = parser.parse_args()
    output = Path(args.output)
    start = time.perf_counter()
    for dataset in args.datasets:
        source = VERSE if dataset == "vertebrae" else VSD
        git = source.git_dir(args.mirrors)
        print(f"\n{dataset}: {source.repository} {git_commit(git, source.commit)} ({source.licence})")
        if dataset == "vertebrae":
            cases = vertebra_cases(git)
        else:
            cases = vsd_cases(git, dataset, not args.no_mirror, args.keep_duplicate)
        export(dataset, cases, output)
    print(f"\nwritten to {output} in {time.perf_counter() - start:.1f} s")


if __name__ == "__main__":
    main()
