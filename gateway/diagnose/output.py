"""Writing a diagnosis: report (Markdown, JSON), figures and the extended model file, into one folder."""

from __future__ import annotations

import json
from collections.abc import Sequence
from pathlib import Path
from typing import Any

from gateway.diagnose.api import Diagnosis, Validation
from gateway.diagnose.plots import write_figures
from gateway.diagnose.report import to_json, to_markdown
from gateway.model import save_model


def write_report(d: Diagnosis, out_dir: str | Path, *, model_name: str = "model", title: str = "",
                 figures: bool = True, extra: dict[str, Any] | None = None, validations: Sequence[Validation] = (),
                 hedges: Sequence[str] = (), profile: str = "", recording_options: str = "") -> dict[str, Path]:
    """Write ``report.md``, ``report.json``, the PNGs and ``<model_name>.diagnosed.model.toml``.

    ``hedges``: caveats the reader must see with every figure (e.g. a window length that was assumed).
    ``profile``, ``recording_options``: the profile's path and the options the recordings were read with, as
    given, for the commands the report prints (run from the same folder).
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    model_file = out / f"{model_name}.diagnosed.model.toml"
    save_model(d.extended, model_file)
    names = write_figures(d, out, validations=validations, hedge="; ".join(hedges)) if figures else []
    doc = to_json(d, figures=names, model_file=model_file.name, validations=validations) | (extra or {})
    (out / "report.json").write_text(json.dumps(doc, indent=2) + "\n", encoding="utf-8")
    (out / "report.md").write_text(to_markdown(d, figures=names, model_file=model_file.name, title=title,
                                               validations=validations, hedges=hedges, profile=profile,
                                               model_path=str(model_file), recording_options=recording_options),
                                   encoding="utf-8")
    return {"report": out / "report.md", "json": out / "report.json", "model": model_file,
            **{n: out / n for n in names}}
