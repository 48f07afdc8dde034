"""Start-up: the ``zernet`` command imports heavy optional libraries only where they are used (issue 34).

PyTorch Geometric compiles TorchScript classes when imported (seconds on a CPU, tens of seconds measured on
a CUDA machine) and matplotlib's pyplot takes half a second: neither may be paid by ``zernet --help``,
``zernet train`` of a ZerNet model or ``zernet predict``.
"""

import subprocess
import sys

HEAVY = ("torch_geometric", "matplotlib", "torch._dynamo", "anny", "trimesh")


def test_cli_import_leaves_heavy_optional_libraries_out():
    code = (
        f"import sys, zernet.cli, zernet.training, zernet.nn; print(','.join(m for m in {HEAVY!r} if m in sys.modules))"
    )
    loaded = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True).stdout.strip()
    assert loaded == "", f"imported at start-up: {loaded}"


def test_feastnet_still_builds_with_its_lazy_import():
    from zernet.nn.models import build_model

    model = build_model("feastnet", in_channels=3, out_channels=4, widths=(8, 8, 16))
    assert type(model.convs[0]).__name__ == "FeaStConv"
