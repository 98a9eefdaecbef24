"""Bring-your-own models: ONNX Runtime (.onnx) and torch.export (.pt2) hosts, `depth-fusion
export`, and the one-line errors of models that cannot be loaded."""

from __future__ import annotations

import logging
from pathlib import Path

import numpy as np
import pytest
import torch
from torch import nn

from depth_fusion_ros.cli.main import main as cli_main
from depth_fusion_ros.singleview.metadata import ModelMetadata, write_metadata_yaml
from depth_fusion_ros.singleview.onnx_model import export_onnx, select_providers
from depth_fusion_ros.singleview.predictor import load_predictor
from depth_fusion_ros.singleview.pt2_model import export_pt2

onnx = pytest.importorskip('onnx')
pytest.importorskip('onnxruntime')
from onnx import TensorProto, helper  # noqa: E402

pytestmark = pytest.mark.usefixtures('one_torch_thread')


def tiny_onnx(path: Path, shape: list, *, op: str = 'mean', meta: ModelMetadata | None = None) -> Path:
    """A hand-built ONNX graph (no exporter): depth = 2 + mean over channels of the normalised
    image, (B, 3, H, W) -> (B, 1, H, W). ``shape`` holds ints or symbolic names. ``op='reshape'``
    adds a reshape to a fixed 48x64 grid, so the model fails on any other size at run time."""
    inp = helper.make_tensor_value_info('image', TensorProto.FLOAT, shape)
    out = helper.make_tensor_value_info('depth', TensorProto.FLOAT, None)
    two = helper.make_tensor('two', TensorProto.FLOAT, [], [2.0])
    axes = helper.make_tensor('axes', TensorProto.INT64, [1], [1])
    nodes = [
        helper.make_node('ReduceMean', ['image', 'axes'], ['m'], keepdims=1),
        helper.make_node('Add', ['m', 'two'], ['d' if op == 'reshape' else 'depth']),
    ]
    inits = [two, axes]
    if op == 'reshape':
        inits.append(helper.make_tensor('grid', TensorProto.INT64, [4], [1, 1, 48, 64]))
        nodes.append(helper.make_node('Reshape', ['d', 'grid'], ['depth']))
    graph = helper.make_graph(nodes, 'tiny', [inp], [out], initializer=inits)
    model = helper.make_model(graph, opset_imports=[helper.make_opsetid('', 18)])
    model.ir_version = 9
    onnx.save(model, str(path))
    write_metadata_yaml(meta or ModelMetadata(input_width=64, input_height=48), path.with_suffix('.yaml'))
    return path


def expected_tiny(rgb: np.ndarray, meta: ModelMetadata) -> np.ndarray:
    x = rgb.astype(np.float32)[..., ::-1] if meta.channel_order == 'bgr' else rgb.astype(np.float32)
    x = (x / meta.pixel_scale - np.array(meta.mean, np.float32)) / np.array(meta.std, np.float32)
    return 2.0 + x.mean(axis=2)


def _rgb(h: int, w: int, seed: int = 0) -> np.ndarray:
    return np.random.default_rng(seed).integers(0, 256, (h, w, 3), dtype=np.uint8)


class _SmallNet(nn.Module):
    """A tiny conv net with a positive output (metres), to export through torch's exporters."""

    def __init__(self) -> None:
        super().__init__()
        torch.manual_seed(0)
        self.conv1 = nn.Conv2d(3, 4, 3, padding=1)
        self.conv2 = nn.Conv2d(4, 1, 3, padding=1, stride=2)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return 0.5 + nn.functional.softplus(self.conv2(torch.relu(self.conv1(x))))


# --- ONNX Runtime host ---------------------------------------------------------------------


def test_onnx_model_follows_its_yaml_channel_order_normalisation_and_batch(tmp_path):
    meta = ModelMetadata(input_width=64, input_height=48, channel_order='bgr', mean=(0.1, 0.2, 0.3))
    path = tiny_onnx(tmp_path / 'tiny.onnx', ['batch', 3, 48, 64], meta=meta)
    predictor = load_predictor(path)
    assert predictor.output_kind == 'metric_depth' and predictor.name == 'tiny.onnx'
    images = [_rgb(48, 64, s) for s in range(3)]
    for rgb, out in zip(images, predictor.predict_batch(images), strict=True):
        np.testing.assert_allclose(out, expected_tiny(rgb, meta), rtol=1e-5)


def test_onnx_fixed_batch_runs_image_by_image_and_dynamic_size_is_rounded(tmp_path):
    fixed = load_predictor(tiny_onnx(tmp_path / 'fixed.onnx', [1, 3, 48, 64]))
    images = [_rgb(48, 64, s) for s in range(3)]
    outs = fixed.predict_batch(images)
    assert len(outs) == 3 and not np.allclose(outs[0], outs[1])
    meta = ModelMetadata(input_width=64, input_height=48, dynamic_input=True, size_multiple=14)
    dyn = load_predictor(tiny_onnx(tmp_path / 'dyn.onnx', ['b', 3, 'h', 'w'], meta=meta))
    assert dyn.metadata.network_size(100, 50) == (98, 56)
    rgb = _rgb(56, 98)  # already a multiple of 14: fed as it is, no resize anywhere
    np.testing.assert_allclose(dyn.predict(rgb), expected_tiny(rgb, meta), rtol=1e-5)
    assert dyn.predict(_rgb(50, 100)).shape == (50, 100)


def test_cuda_without_the_onnx_cuda_provider_is_a_notice_and_cpu(caplog):
    import onnxruntime as ort

    if 'CUDAExecutionProvider' in ort.get_available_providers():
        providers = select_providers(torch.device('cuda:0'))
        assert providers[0][0] == 'CUDAExecutionProvider'
        return
    with caplog.at_level(logging.WARNING):
        assert select_providers(torch.device('cuda:0')) == ['CPUExecutionProvider']
    notices = [r.getMessage() for r in caplog.records if 'CUDAExecutionProvider' in r.getMessage()]
    assert len(notices) == 1 and 'CPU' in notices[0] and '\n' not in notices[0]
    assert select_providers(torch.device('cpu')) == ['CPUExecutionProvider']


def test_tiny_network_exported_to_onnx_and_pt2_agrees_with_eager(tmp_path):
    net = _SmallNet().eval()
    meta = ModelMetadata(input_width=64, input_height=48, depth_max=100.0)
    example = torch.zeros(1, 3, 48, 64)
    export_onnx(net, tmp_path / 'small.onnx', example)
    export_pt2(net, tmp_path / 'small.pt2', example)
    for p in ('small.onnx', 'small.pt2'):
        write_metadata_yaml(meta, (tmp_path / p).with_suffix('.yaml'))
    images = [_rgb(48, 64, s) for s in range(2)]
    eager = load_predictor(tmp_path / 'small.onnx')
    x = eager.preprocess(images)
    with torch.no_grad():
        reference = net(x).numpy()[:, 0]
    for name in ('small.onnx', 'small.pt2'):
        predictor = load_predictor(tmp_path / name)
        assert [o.shape for o in predictor.predict_batch(images)] == [(48, 64)] * 2  # dynamic batch
        with torch.no_grad():
            raw = predictor.module(x).numpy()[:, 0]
        np.testing.assert_allclose(raw, reference, rtol=1e-4)


# --- depth-fusion export on the shipped network ---------------------------------------------


@pytest.fixture(scope='module')
def exported(tmp_path_factory) -> dict[str, Path]:
    out = tmp_path_factory.mktemp('export')
    paths = {}
    for fmt, name in (('onnx', 'compact.onnx'), ('pt2', 'compact.pt2'), ('torchscript', 'compact_ts.pt')):
        assert cli_main(['export', '--format', fmt, '--out', str(out / name)]) == 0
        paths[fmt] = out / name
    return paths


def test_exported_shipped_network_agrees_with_eager_on_demo_keyframes(exported, synthetic_sequence, capsys):
    eager = load_predictor('default')
    frames = [synthetic_sequence.frames[i].rgb for i in range(0, len(synthetic_sequence), 6)]
    x = eager.preprocess(frames)
    with torch.no_grad():
        reference = eager.module(x).numpy()
    for fmt, path in exported.items():
        assert path.with_suffix('.yaml').is_file(), fmt
        predictor = load_predictor(path)
        with torch.no_grad():
            raw = predictor.module(x).numpy()
        rel = np.abs(raw - reference) / np.abs(reference)
        assert rel.max() <= 1e-4, (fmt, float(rel.max()))
        for frame, out in zip(frames, predictor.predict_batch(frames), strict=True):
            np.testing.assert_allclose(out, eager.predict(frame), rtol=1e-4)


def test_exported_model_works_as_single_view_source(exported, synthetic_sequence):
    from depth_fusion_ros.evaluation.context import EvalOptions
    from depth_fusion_ros.evaluation.harness import evaluate_sequence

    results = {}
    for spec in ('default', str(exported['onnx'])):
        options = EvalOptions(frames=24, keyframes=[0, 12], single_view=spec)
        res = evaluate_sequence(synthetic_sequence, ['single_view'], options, show_progress=False)
        results[spec] = res.records['single_view'].all.summary()['mae']
    assert results['default'] == pytest.approx(results[str(exported['onnx'])], rel=1e-4)


def test_export_rejects_a_suffix_that_does_not_match_the_format(tmp_path, capsys):
    assert cli_main(['export', '--format', 'onnx', '--out', str(tmp_path / 'x.pt2')]) == 1
    err = capsys.readouterr().err.strip()
    assert err.count('\n') == 0 and 'x.pt2' in err and '.onnx' in err
    assert cli_main(['export', '--out', str(tmp_path / 'x.onnx'), '--model', str(tmp_path / 'no.pt')]) == 1
    assert 'no.pt' in capsys.readouterr().err


# --- models that cannot be loaded: one line naming the file and the reason --------------------


def _pt2_fixed(path: Path) -> Path:
    export_pt2(_SmallNet(), path, torch.zeros(1, 3, 48, 64))
    write_metadata_yaml(ModelMetadata(input_width=320, input_height=240), path.with_suffix('.yaml'))
    return path


BROKEN = {
    'missing onnx': (lambda d: d / 'nowhere.onnx', FileNotFoundError, r'nowhere\.onnx'),
    'missing pt2': (lambda d: d / 'nowhere.pt2', FileNotFoundError, r'nowhere\.pt2'),
    'missing yaml': (
        lambda d: (tiny_onnx(d / 'noyaml.onnx', ['b', 3, 48, 64]), (d / 'noyaml.yaml').unlink())[0],
        FileNotFoundError,
        r'metadata YAML for ONNX model .*noyaml\.onnx not found: expected .*noyaml\.yaml',
    ),
    'wrong yaml': (
        lambda d: (
            tiny_onnx(d / 'badyaml.onnx', ['b', 3, 48, 64]),
            (d / 'badyaml.yaml').write_text('input_width: 64\ninput_height: 48\noutput_kind: disparity\n'),
        )[0],
        ValueError,
        r'badyaml\.yaml: .*output_kind must be one of',
    ),
    'yaml not a mapping': (
        lambda d: (tiny_onnx(d / 'list.onnx', ['b', 3, 48, 64]), (d / 'list.yaml').write_text('- 1\n'))[0],
        ValueError,
        r'list\.yaml: expected a mapping',
    ),
    'onnx input size differs from yaml': (
        lambda d: tiny_onnx(d / 'size.onnx', [1, 3, 48, 64], meta=ModelMetadata()),
        ValueError,
        r'size\.onnx: the model takes 64x48 images but its YAML says .* 320x240',
    ),
    'onnx not an image input': (
        lambda d: tiny_onnx(d / 'chan.onnx', [1, 4, 48, 64]),
        ValueError,
        r'chan\.onnx: input .* has 4 channels',
    ),
    'onnx rejects the input at run time': (
        lambda d: tiny_onnx(d / 'reshape.onnx', ['b', 3, 'h', 'w'], op='reshape', meta=ModelMetadata()),
        ValueError,
        r'reshape\.onnx: the network fails on a 320x240 input',
    ),
    'corrupt onnx': (
        lambda d: (d / 'junk.onnx').write_bytes(b'not a protobuf at all' * 10) and _yaml(d / 'junk.onnx'),
        ValueError,
        r'junk\.onnx: not a loadable ONNX model',
    ),
    'pt2 input size differs from yaml': (
        lambda d: _pt2_fixed(d / 'fixed.pt2'),
        ValueError,
        r'fixed\.pt2: the program takes 64x48 images but its YAML says .* 320x240',
    ),
    'corrupt pt2': (
        lambda d: (d / 'junk.pt2').write_bytes(b'PK\x03\x04 truncated') and _yaml(d / 'junk.pt2'),
        ValueError,
        r'junk\.pt2: not a loadable torch.export program',
    ),
}


def _yaml(path: Path) -> Path:
    write_metadata_yaml(ModelMetadata(), path.with_suffix('.yaml'))
    return path


@pytest.mark.parametrize('case', sorted(BROKEN))
def test_a_model_that_cannot_be_loaded_is_one_line_naming_file_and_reason(case, tmp_path):
    make, error, pattern = BROKEN[case]
    path = make(tmp_path)
    with pytest.raises(error, match=pattern) as info:
        load_predictor(path)
    assert '\n' not in str(info.value)


@pytest.mark.parametrize('command', ['evaluate', 'run', 'demo'])
def test_cli_fails_at_start_with_one_line_for_a_broken_model(command, tmp_path, capsys):
    path = tiny_onnx(tmp_path / 'size.onnx', [1, 3, 48, 64], meta=ModelMetadata())
    args = {
        'evaluate': ['evaluate', str(tmp_path / 'no_such_sequence'), '--single-view', str(path)],
        'run': ['run', '--bag', str(tmp_path / 'no_such_bag'), '--single-view', str(path)],
        'demo': ['demo', '--out', str(tmp_path / 'demo'), '--single-view', str(path)],
    }[command]
    assert cli_main(args) == 1
    err = capsys.readouterr().err.strip()
    assert err.count('\n') == 0, err
    assert f'depth-fusion {command}: error: {path}: the model takes 64x48 images' in err
    assert not (tmp_path / 'demo').exists()  # nothing was started


def test_node_fails_at_start_with_one_line_for_a_broken_model(tmp_path):
    import subprocess
    import sys

    path = tiny_onnx(tmp_path / 'size.onnx', [1, 3, 48, 64], meta=ModelMetadata())
    proc = subprocess.run(
        [
            sys.executable,
            '-m',
            'depth_fusion_ros.nodes.single_view_node',
            '--ros-args',
            '-p',
            f'model:={path}',
        ],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert proc.returncode == 2, proc.stderr
    errors = [line for line in (proc.stdout + proc.stderr).splitlines() if 'ERROR' in line]
    assert len(errors) == 1 and str(path) in errors[0] and 'takes 64x48 images' in errors[0]
