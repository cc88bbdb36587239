"""The worked example of docs/discrepancy.md, with its figures.

    python -m tactile_deploy.calibration.discrepancy.figure [--out docs/img/discrepancy] [--contacts 40]

The shipped virtual sensor ``gelslim1`` is the model; "measured" presses come from the same
sensor with a domed gel (``dome``, 0.3 mm sag at the rim) that the model lacks.
The workflow runs on them (report figures into ``--out``), the effect it finds is applied to a
copy of the model, and the workflow runs again on the same data with the new model. Both
verdicts are written as text beside the figures and into their marked blocks of ``--doc``
(``<!-- example:verdict_before -->`` ... ``<!-- /example:verdict_before -->``).
"""

from __future__ import annotations

import argparse
import shutil
import tempfile
from pathlib import Path

ROOT = Path(__file__).resolve().parents[2]


def _markers(doc: Path, name: str) -> tuple[str, str]:
    begin, end = f"<!-- example:{name} -->", f"<!-- /example:{name} -->"
    content = doc.read_text()
    if begin not in content or end not in content:
        raise SystemExit(f"{doc}: markers {begin} and {end} not found; add them where the "
                         f"text of {name} belongs")
    return begin, end


def fill_block(doc: Path, name: str, text: str) -> None:
    """Replace the fenced text between ``<!-- example:NAME -->`` and its end marker in ``doc``."""
    from tactile_deploy.atomic import atomic_path, write_text

    begin, end = _markers(doc, name)
    head, rest = doc.read_text().split(begin, 1)
    _, tail = rest.split(end, 1)
    write_text(doc, f"{head}{begin}\n```\n{text.rstrip()}\n```\n{end}{tail}")


def main(argv=None) -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--out", type=Path, default=ROOT / "docs" / "img" / "discrepancy")
    parser.add_argument("--contacts", type=int, default=40)
    parser.add_argument("--workers", type=int, default=2)
    parser.add_argument("--doc", type=Path, default=ROOT / "docs" / "discrepancy.md",
                        help="markdown file whose example blocks receive the verdicts")
    args = parser.parse_args(argv)
    if args.doc.exists():  # refuse before the runs, not after
        for name in ("verdict_before", "verdict_after"):
            _markers(args.doc, name)

    from tactile_deploy.calibration.discrepancy.apply import apply_effect
    from tactile_deploy.calibration.discrepancy.measured import save_measured
    from tactile_deploy.calibration.discrepancy.report import write_report
    from tactile_deploy.calibration.discrepancy.synthetic import hidden_effect_data, random_contacts
    from tactile_deploy.calibration.discrepancy.verdict import verdict_text
    from tactile_deploy.calibration.discrepancy.workflow import DiscrepancyOptions, find_discrepancy
    from tactile_deploy.atomic import write_text
    from tactile_deploy.sensors import load_sensor
    from tactile_deploy.sensors.config import EffectSpec, load_sensor_config
    from tactile_deploy.sensors.virtual import VirtualSensor

    sensor = load_sensor("gelslim1")
    contacts = random_contacts(args.contacts, 11, radius_mm=8.0, depth_range_mm=(0.3, 1.0))
    hidden = EffectSpec(name="dome", params={"height_mm": 0.3})
    data = hidden_effect_data(sensor, [hidden], contacts, 0.005, 11)
    args.out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        save_measured(Path(tmp) / "presses.npz", data)
        opts = DiscrepancyOptions(workers=args.workers)
        before = find_discrepancy(sensor, data, opts)
        for path in write_report(before, Path(tmp) / "report"):  # the figures and verdict.json
            if path.name != "report.md":
                with atomic_path(args.out / path.name) as dst:
                    shutil.copyfile(path, dst)
        applied = apply_effect("gelslim1", sensor.config, before.verification.spec,
                               {"example": True}, Path(tmp))
        updated = VirtualSensor(load_sensor_config(applied.path), simulator=sensor.simulator)
        after = find_discrepancy(updated, data, opts)
    for name, result in (("verdict_before", before), ("verdict_after", after)):
        write_text(args.out / f"{name}.txt", verdict_text(result.verdict) + "\n")
        if args.doc.exists():
            fill_block(args.doc, name, verdict_text(result.verdict))
    print(verdict_text(before.verdict))
    print(verdict_text(after.verdict))


if __name__ == "__main__":
    main()
