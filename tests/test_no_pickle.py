"""No pickle anywhere: not on the wire, not in checkpoints read from disk, not in the package.

A static scan of every module of the installed ``fedhpg.*`` packages (the syntax tree, so
docstrings saying "no pickle" do not count), a check that the scan catches what it looks for,
and the two places bytes from outside come in, fed a pickle that would leave a file behind if
anything unpickled it: the wire codec and the checkpoint loader. They also run with every
unpickling entry point disabled."""

from __future__ import annotations

import ast
import hashlib
import importlib.util
import pickle
from pathlib import Path

import msgpack
import numpy as np
import pytest
import torch

from fedhpg.common.records.types import UpdateColumns, UpdateStats
from fedhpg.common.wire.codec import ProtocolError, decode, encode
from fedhpg.common.wire.protocol import PROTOCOL_VERSION, Update
from fedhpg.server.checkpoint import (
    Checkpoint,
    CheckpointError,
    load_checkpoint,
    save_checkpoint,
)

PACKAGES = ("fedhpg.common", "fedhpg.envs", "fedhpg.server", "fedhpg.agent", "fedhpg.conf")
BANNED_MODULES = frozenset(
    {"pickle", "_pickle", "cPickle", "cloudpickle", "dill", "marshal", "shelve", "joblib"}
    | {"jsonpickle", "copyreg", "torch.serialization", "multiprocessing.reduction"}
)
BANNED_CALLS = {
    ("torch", "load"): "torch.load unpickles",
    ("torch", "save"): "torch.save writes a pickle",
    ("yaml", "load"): "yaml.load builds arbitrary objects (use safe_load)",
    ("yaml", "unsafe_load"): "yaml.unsafe_load builds arbitrary objects",
}
BANNED_ATTRIBUTES = {
    "send_pyobj": "zmq's send_pyobj pickles",
    "recv_pyobj": "zmq's recv_pyobj unpickles",
    "loads_pyobj": "pickles",
}


def _name(node: ast.AST) -> str | None:
    return node.id if isinstance(node, ast.Name) else None


def offences(source: str, filename: str = "<source>") -> list[str]:
    """Every pickle-capable construct in ``source``, as 'file:line: what'."""
    tree = ast.parse(source, filename)
    found: list[str] = []
    uses_multiprocessing = False

    def flag(node: ast.AST, what: str) -> None:
        found.append(f"{filename}:{getattr(node, 'lineno', '?')}: {what}")

    for node in ast.walk(tree):
        if isinstance(node, ast.Import | ast.ImportFrom):
            modules = (
                [alias.name for alias in node.names]
                if isinstance(node, ast.Import)
                else [node.module or ""] + [f"{node.module}.{a.name}" for a in node.names]
            )
            uses_multiprocessing |= any(m.split(".")[0] == "multiprocessing" for m in modules)
            for module in modules:
                if module in BANNED_MODULES or module.split(".")[0] in BANNED_MODULES:
                    flag(node, f"imports {module}")
        elif isinstance(node, ast.Attribute):
            owner = _name(node.value)
            if owner in ("np", "numpy") and node.attr == "load":
                flag(node, "numpy.load (can unpickle; the codec uses frombuffer)")
            if owner is not None and (owner, node.attr) in BANNED_CALLS:
                flag(node, BANNED_CALLS[(owner, node.attr)])
            if node.attr in BANNED_ATTRIBUTES:
                flag(node, BANNED_ATTRIBUTES[node.attr])
        elif isinstance(node, ast.keyword) and node.arg == "allow_pickle":
            if not (isinstance(node.value, ast.Constant) and node.value.value is False):
                flag(node, "allow_pickle other than False")
        elif isinstance(node, ast.Call) and _dynamic_import(node):
            flag(node, f"imports {_dynamic_import(node)} dynamically")
    if uses_multiprocessing:
        # multiprocessing.Connection.send/recv pickle; send_bytes/recv_bytes do not.
        for node in ast.walk(tree):
            if isinstance(node, ast.Attribute) and node.attr in ("send", "recv"):
                flag(node, f"Connection.{node.attr} pickles (use {node.attr}_bytes)")
    return found


def _dynamic_import(node: ast.Call) -> str | None:
    func = node.func
    is_import = _name(func) == "__import__" or (
        isinstance(func, ast.Attribute) and func.attr == "import_module"
    )
    if is_import and node.args and isinstance(node.args[0], ast.Constant):
        module = str(node.args[0].value)
        if module.split(".")[0] in BANNED_MODULES or module in BANNED_MODULES:
            return module
    return None


def _package_modules() -> list[Path]:
    files: list[Path] = []
    for package in PACKAGES:
        spec = importlib.util.find_spec(package)
        assert spec is not None and spec.submodule_search_locations, package
        for location in spec.submodule_search_locations:
            files += sorted(Path(location).rglob("*.py"))
    return files


def test_the_package_has_no_pickle_anywhere() -> None:
    files = _package_modules()
    names = {f"{f.parent.name}/{f.name}" for f in files}
    # The scan really covers the wire, the checkpoints and the launcher.
    assert {"wire/codec.py", "server/checkpoint.py", "commands/launcher.py"} <= names
    assert len(files) > 30, files
    found = [hit for path in files for hit in offences(path.read_text(), str(path))]
    assert found == [], "\n".join(found)


@pytest.mark.parametrize(
    "snippet",
    [
        "import pickle",
        "import cloudpickle as cp",
        "from marshal import loads",
        "from torch import serialization",
        "import torch\ntorch.load('x.pt')",
        "import torch\ntorch.save({}, 'x.pt')",
        "import numpy as np\nnp.load('x.npy', allow_pickle=True)",
        "import numpy as np\nnp.load('x.npy')",
        "import yaml\nyaml.load(text)",
        "socket.recv_pyobj()",
        "importlib.import_module('pickle')",
        "__import__('dill')",
        "import multiprocessing\nreceive.recv()",
        "from multiprocessing import Pipe\nserve(on_bound=ready.send)",
    ],
)
def test_the_scan_catches_each_kind(snippet: str) -> None:
    assert offences(snippet), snippet


def test_the_scan_leaves_plain_code_alone() -> None:
    clean = (
        '"""No pickle, no torch.load."""\n'
        "import msgpack, numpy as np, zmq\n"
        "np.frombuffer(b'', dtype=np.float32)\n"
        "socket.send_multipart(frames)\n"
        "socket.send(b'x')  # zmq, in a module without multiprocessing\n"
    )
    assert offences(clean) == []


# --- what comes in from outside, fed a pickle ---------------------------------------------------


class _Tripwire:
    """Unpickling this creates ``marker``: proof that something unpickled it."""

    def __init__(self, marker: Path) -> None:
        self.marker = marker

    def __reduce__(self) -> tuple:
        return (open, (str(self.marker), "w"))


def _armed(marker: Path) -> bytes:
    payload = pickle.dumps(_Tripwire(marker))
    pickle.loads(payload).close()  # the tripwire works...
    assert marker.exists()
    marker.unlink()  # ...and is re-armed
    return payload


def test_a_pickle_on_the_wire_is_refused_unopened(tmp_path: Path) -> None:
    marker = tmp_path / "unpickled"
    payload = _armed(marker)
    header = msgpack.packb(
        {
            "v": PROTOCOL_VERSION,
            "type": "update",
            "fields": {"round": 1, "stats": {}},
            "arrays": [{"field": "theta", "dtype": "|O", "shape": [1]}],
        }
    )
    for frames in ([payload], [header, payload], [header, b"\x00" * 8]):
        with pytest.raises(ProtocolError):
            decode(frames)
    assert not marker.exists()


def test_a_pickle_as_a_checkpoint_is_refused_unopened(tmp_path: Path) -> None:
    marker = tmp_path / "unpickled"
    payload = _armed(marker)
    torch_file = tmp_path / "torch.ckpt"
    torch.save({"theta": _Tripwire(marker)}, torch_file)  # what a torch checkpoint would be
    object_array = msgpack.packb(
        {
            "format": "fedhpg-checkpoint",
            "version": 1,
            "round": 1,
            "theta": {"dtype": "|O", "shape": [1], "data": payload},
            "config": {},
            "metrics_lines": 1,
            "state": {},
        }
    )
    cases = {
        "round-000001.safetensors": payload,
        "raw.ckpt": payload,
        "checksummed.ckpt": hashlib.sha256(payload).digest() + payload,
        "object-dtype.ckpt": hashlib.sha256(object_array).digest() + object_array,
    }
    for name, data in cases.items():
        (tmp_path / name).write_bytes(data)
    for path in [torch_file, *(tmp_path / name for name in cases)]:
        with pytest.raises(CheckpointError):
            load_checkpoint(path)
    assert not marker.exists()


def test_wire_and_checkpoints_work_with_unpickling_disabled(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch
) -> None:
    def forbidden(*args: object, **kwargs: object) -> None:
        raise AssertionError("something unpickled")

    for owner, name in [
        (pickle, "loads"),
        (pickle, "load"),
        (pickle, "Unpickler"),
        (torch, "load"),
        (np, "load"),
    ]:
        monkeypatch.setattr(owner, name, forbidden)
    theta = torch.arange(12, dtype=torch.float32)
    path = save_checkpoint(
        tmp_path,
        Checkpoint(round=3, theta=theta, config={"seed": 1}, metrics_lines=3, state={}),
    )
    loaded = load_checkpoint(path)
    assert torch.equal(loaded.theta, theta) and loaded.config == {"seed": 1}
    stats = UpdateStats(trajectories=1, env_steps=1, compute_s=0.0, train_return=0.0)
    update = Update(
        round=1, agents=[0], thetas=theta.numpy()[None], stats=UpdateColumns.of([stats])
    )
    decoded = decode([bytes(f) for f in encode(update)])
    assert isinstance(decoded, Update) and np.array_equal(decoded.thetas, update.thetas)
