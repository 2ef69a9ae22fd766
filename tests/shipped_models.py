"""Models directories for the tests of the model ``learned`` resolves per env (issue 58 item 6):
copies of the packaged model shipped under another name for another env id."""

from __future__ import annotations

import json
import shutil
import zipfile
from pathlib import Path

from policies.learned import DEFAULT_MODEL_NAME, DEFAULT_MODEL_PATH


def ship_copy(directory: Path, name: str, env_id: str | None, **config) -> Path:
    """Put a copy of the packaged model in ``directory`` as ``name`` (a ``.zip``) with its
    config JSON, the config's ``env_id`` set to ``env_id`` (None: removed) and ``config``'s
    keys over it; the zip holds one more entry naming the copy, so its bytes (and digest)
    differ from the packaged model's and from every other copy's. The fingerprint is kept: it
    is the system the weights were trained on, so the copy matches the code as the packaged
    model does. Returns the zip's path."""
    directory.mkdir(parents=True, exist_ok=True)
    target = directory / name
    if name == DEFAULT_MODEL_NAME:
        shutil.copyfile(DEFAULT_MODEL_PATH, target)  # the packaged model itself
    else:
        with zipfile.ZipFile(DEFAULT_MODEL_PATH) as src, zipfile.ZipFile(target, "w") as dst:
            for item in src.infolist():
                dst.writestr(item, src.read(item))
            dst.writestr("shipped-as.txt", name)
    data = json.loads(DEFAULT_MODEL_PATH.with_suffix(".json").read_text())
    data.pop("env_id", None)
    if env_id is not None:
        data["env_id"] = env_id
    data.update(config)
    target.with_suffix(".json").write_text(json.dumps(data))
    return target
