"""Command line: ``camera`` (estimate a camera mapping) and ``make-board`` (print a ChArUco board).

Registered under ``tactile-deploy calibrate``. Heavy imports (OpenCV, SciPy) happen inside the
commands so that ``--help`` stays fast.
"""

from __future__ import annotations

from enum import Enum
from pathlib import Path
from typing import Optional

import typer

camera_app = typer.Typer(
    help="Camera mapping: lens distortion, homography to the sensor plane, mm per pixel.",
    no_args_is_help=True,
)

_IMAGE_SUFFIXES = {".png", ".jpg", ".jpeg", ".bmp", ".tif", ".tiff"}


def _fail(message: str) -> None:
    typer.echo(f"error: {message}", err=True)
    raise typer.Exit(code=2)


class TargetKind(str, Enum):
    charuco = "charuco"
    dots = "dots"


class BoardFacing(str, Enum):
    camera = "camera"
    outside = "outside"


class SensorAxis(str, Enum):
    plus_x = "+x"
    minus_x = "-x"
    plus_y = "+y"
    minus_y = "-y"


def _parse_pair(text: str, option: str) -> tuple[int, int]:
    try:
        a, b = (int(v) for v in text.lower().split("x"))
    except ValueError:
        raise typer.BadParameter(f"expected COLSxROWS such as 13x13, got {text!r}",
                                 param_hint=option) from None
    if a < 1 or b < 1:
        raise typer.BadParameter(f"counts must be positive, got {text!r}", param_hint=option)
    return a, b


def _read_image(path: Path):
    import cv2

    img = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    if img is None:
        raise typer.BadParameter(f"cannot read image {path}")
    return img


def _list_images(folder: Path) -> list[Path]:
    if not folder.is_dir():
        raise typer.BadParameter(f"{folder} is not a folder", param_hint="--frames")
    files = sorted(p for p in folder.iterdir() if p.suffix.lower() in _IMAGE_SUFFIXES)
    if not files:
        raise typer.BadParameter(
            f"no images ({', '.join(sorted(_IMAGE_SUFFIXES))}) in {folder}", param_hint="--frames"
        )
    return files


@camera_app.command("camera")
def camera(
    frames: Path = typer.Option(..., "--frames", help="Folder of target frames (images)."),
    target: TargetKind = typer.Option(..., "--target", help="charuco (printed board) or dots "
                                      "(grid pressed into the gel)."),
    out: Path = typer.Option(Path("camera_mapping.json"), "--out", help="Mapping JSON to write."),
    pitch_mm: Optional[float] = typer.Option(None, "--pitch-mm", help="dots: lattice pitch, mm."),
    dot_grid: Optional[str] = typer.Option(
        None, "--dot-grid", help="dots: grid size COLSxROWS; checks that every edge dot was seen "
        "(recommended)."),
    reference: Optional[Path] = typer.Option(None, "--reference", help="dots: unpressed frame "
                                             "(default: reference.* in --frames)."),
    board: Optional[Path] = typer.Option(None, "--board", help="charuco: board JSON written by "
                                         "make-board (default: the default board)."),
    plane_frame: Optional[str] = typer.Option(None, "--plane-frame", help="charuco: file name of "
                                              "the frame with the board on the sensor plane "
                                              "(default: first by name)."),
    board_faces: BoardFacing = typer.Option(BoardFacing.camera, "--board-faces", help="charuco: "
                                            "printed side faces the camera or outside."),
    u_axis: SensorAxis = typer.Option(SensorAxis.plus_x, "--u-axis",
                                      help="dots: sensor axis along image right (+-45 deg)."),
    v_axis: SensorAxis = typer.Option(SensorAxis.plus_y, "--v-axis",
                                      help="dots: sensor axis along image down (+-45 deg)."),
    focal_px: Optional[float] = typer.Option(None, "--focal-px", help="Single view: assumed "
                                             "focal length, px (default max(W, H))."),
    blur_px: float = typer.Option(2.5, "--blur-px", help="dots: smoothing before detection, px."),
    figure: Optional[Path] = typer.Option(None, "--figure", help="Also write a PNG of the "
                                          "detections, residuals and rectified frame."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing --out "
                                   "(and --figure) file."),
) -> None:
    """Estimate the camera mapping from frames of a calibration target and write it as JSON."""
    from rich.console import Console
    from rich.table import Table

    from tactile_deploy.calibration.camera.fitting import CalibrationError
    from tactile_deploy.outputs import OutputPathError, check_distinct, check_output_file
    from tactile_deploy.imaging.camera_mapping import save_mapping

    console = Console()
    files = _list_images(frames)
    try:   # the inputs first (cheap), then the outputs, then the fit
        if target is TargetKind.charuco:
            from tactile_deploy.calibration.camera.charuco import CharucoBoardSpec, load_board_spec

            spec = load_board_spec(board) if board is not None else CharucoBoardSpec()
            names = [p.name for p in files]
            plane_index = 0
            if plane_frame is not None:
                if plane_frame not in names:
                    raise typer.BadParameter(f"{plane_frame} is not among {names}",
                                             param_hint="--plane-frame")
                plane_index = names.index(plane_frame)
        else:
            if pitch_mm is None:
                raise typer.BadParameter("--target dots needs --pitch-mm", param_hint="--pitch-mm")
            ref_path = reference
            if ref_path is None:
                refs = [p for p in files if p.stem.lower() == "reference"]
                if not refs:
                    raise typer.BadParameter(
                        f"no reference frame: put the unpressed gel as reference.png in {frames} "
                        "or pass --reference", param_hint="--reference")
                ref_path = refs[0]
            pressed = [p for p in files if p.resolve() != ref_path.resolve()]
            if not pressed:
                raise typer.BadParameter(f"no pressed frames in {frames} besides the reference")
    except (CalibrationError, ValueError, FileNotFoundError) as e:
        typer.echo(f"calibration failed: {e}", err=True)
        raise typer.Exit(code=1) from None
    inputs = [*files, reference, board]
    try:
        check_output_file(out, "--out", overwrite=overwrite, inputs=inputs, suffixes=(".json",))
        if figure is not None:
            check_output_file(figure, "--figure", overwrite=overwrite, inputs=inputs,
                              suffixes=(".png",))
        check_distinct(("--out", out), ("--figure", figure))
    except OutputPathError as e:
        _fail(str(e))
    try:
        if target is TargetKind.charuco:
            from tactile_deploy.calibration.camera.charuco import calibrate_charuco

            images = [_read_image(p) for p in files]
            fit = calibrate_charuco(
                images, spec, plane_index=plane_index,
                board_faces_camera=board_faces is BoardFacing.camera,
                focal_px=focal_px, names=names,
            )
            shown = images[plane_index]
        else:
            from tactile_deploy.calibration.camera.dots import calibrate_dots

            images = [_read_image(p) for p in pressed]
            fit, _ = calibrate_dots(
                images, _read_image(ref_path), pitch_mm,
                grid_shape=_parse_pair(dot_grid, "--dot-grid") if dot_grid else None,
                u_axis=u_axis.value, v_axis=v_axis.value, focal_px=focal_px,
                blur_sigma_px=blur_px,
                name=pressed[0].name,
            )
            shown = images[0]
    except (CalibrationError, ValueError, FileNotFoundError) as e:
        typer.echo(f"calibration failed: {e}", err=True)
        raise typer.Exit(code=1) from None

    save_mapping(fit.mapping, out)
    m, s = fit.mapping, fit.mapping.fit
    table = Table(title=f"camera mapping -> {out}", show_header=False)
    for key, value in [
        ("method",
         f"{s.method}, {s.n_frames} frame(s), {s.n_points} points ({s.n_rejected} rejected)"),
        ("mm per px (x, y)", f"{m.mm_per_px_x:.5f}, {m.mm_per_px_y:.5f}"),
        ("reprojection RMS",
         f"{s.rms_px:.3f} px (max {s.max_px:.3f} px), {s.rms_mm * 1000:.1f} um"),
        ("image mirrored", str(m.image_mirrored)),
        ("output grid in view", f"{100 * s.grid_coverage:.1f} %"),
    ]:
        table.add_row(key, value)
    console.print(table)
    if s.grid_coverage < 1.0:
        console.print("[yellow]warning:[/yellow] part of the output grid lies outside the image; "
                      "those cells repeat the nearest edge pixel")
    if figure is not None:
        from tactile_deploy.calibration.camera.figure import plot_fit

        plot_fit(fit, shown, figure)
        console.print(f"figure -> {figure}")


@camera_app.command("make-board")
def make_board(
    out: Path = typer.Option(Path("board.png"), "--out", help="PNG to write (+ a .json beside)."),
    dpi: int = typer.Option(600, "--dpi", min=150, help="Printer resolution, dots per inch."),
    squares: str = typer.Option("14x14", "--squares", help="Squares COLSxROWS."),
    square_mm: float = typer.Option(3.0, "--square-mm", help="Square side, mm."),
    marker_mm: float = typer.Option(2.25, "--marker-mm", help="Marker side, mm."),
    dictionary: str = typer.Option("DICT_4X4_100", "--dictionary", help="ArUco dictionary."),
    overwrite: bool = typer.Option(False, "--overwrite", help="Replace an existing --out PNG "
                                   "and the JSON beside it."),
) -> None:
    """Write a print-ready ChArUco board (true size at --dpi) and its description JSON."""
    from pydantic import ValidationError

    from tactile_deploy.calibration.camera.charuco import CharucoBoardSpec, save_print_sheet
    from tactile_deploy.outputs import OutputPathError, check_output_file

    try:
        check_output_file(out, "--out", overwrite=overwrite, suffixes=(".png",))
        check_output_file(out.with_suffix(".json"), "--out", overwrite=overwrite)
    except OutputPathError as e:
        _fail(str(e))
    cols, rows = _parse_pair(squares, "--squares")
    try:
        spec = CharucoBoardSpec(squares_x=cols, squares_y=rows, square_mm=square_mm,
                                marker_mm=marker_mm, dictionary=dictionary)
    except ValidationError as e:
        raise typer.BadParameter("; ".join(err["msg"] for err in e.errors())) from None
    width_mm, height_mm = save_print_sheet(spec, out, dpi)
    typer.echo(f"{out}: {spec.describe()}; print at 100 % ({dpi} dpi): board "
               f"{width_mm:.2f} x {height_mm:.2f} mm; description {out.with_suffix('.json')}")
