"""The MKL VML warm-up (vml_warmup.py): done on import of the compute entry modules, before
any parallel unary op, and the first parallel sqrt then gives the one-thread, high-accuracy result.

The race it prevents (a concurrent first call running the low-accuracy kernel on one thread's
chunk) is timing-dependent and rare (a few percent of fresh processes here), so it is not
provoked in a test; see the module docstring.
"""

from __future__ import annotations

import subprocess
import sys

import pytest

_PROBE = """
import importlib, sys
module = importlib.import_module(sys.argv[1])
assert sys.modules['depth_fusion_ros.vml_warmup']._done, sys.argv[1]
import torch
x = torch.rand(300_000, generator=torch.Generator().manual_seed(0)) + 1e-3
first = torch.sqrt(x)  # the process's first large sqrt: parallel chunks when threads > 1
torch.set_num_threads(1)
assert torch.equal(first, torch.sqrt(x)), 'the first parallel sqrt differs from a one-thread one'
assert float(((first.double() - x.double().sqrt()).abs() / x.double().sqrt()).max()) < 1e-6
print('ok')
"""

ENTRY_MODULES = (
    'depth_fusion_ros.multiview.cost_volume',
    'depth_fusion_ros.multiview.descriptors',
    'depth_fusion_ros.fusion.pipeline',
    'depth_fusion_ros.singleview.torchscript_model',
)


@pytest.mark.parametrize('module', ENTRY_MODULES)
def test_entry_module_warms_up_before_the_first_parallel_sqrt(module):
    out = subprocess.run(
        [sys.executable, '-c', _PROBE, module], capture_output=True, text=True, check=True, timeout=120
    )
    assert out.stdout.strip() == 'ok'
