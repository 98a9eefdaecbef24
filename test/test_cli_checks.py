"""Bad input refused before any work, in one line: output paths, ``--set`` names, ``--frames``,
a bag that lacks a topic the graph needs, and pinned dependencies."""

from __future__ import annotations

import errno
import re
import tempfile
from pathlib import Path

import pytest

from depth_fusion_ros.cli.main import main
from depth_fusion_ros.cli.overrides import check_node_overrides, check_params_file, check_stage_overrides
from depth_fusion_ros.cli.paths import OutputPathError, check_output
from depth_fusion_ros.nodes.graph import RunOptions
from depth_fusion_ros.nodes.graph.inputs import MissingInputError, check_inputs, missing_inputs

ROOT = Path(__file__).resolve().parents[1]
ALL = ['/camera/rgb/image_color', '/camera/rgb/camera_info', '/camera/pose', '/camera/depth/image']


CONFIG = Path(__file__).resolve().parents[1] / 'config' / 'depth_fusion.yaml'


def one_line_error(capsys, argv: list[str], code: int = 1) -> str:
    if code == 2:  # argparse
        with pytest.raises(SystemExit) as exc:
            main(argv)
        assert exc.value.code == 2
    else:
        assert main(argv) == code
    err = capsys.readouterr().err.strip().splitlines()
    assert err and 'Traceback' not in '\n'.join(err)
    return err[-1]


# --- output paths -----------------------------------------------------------------------------


def test_output_under_a_file_existing_and_bag_suffix(tmp_path):
    (tmp_path / 'file').write_text('x')
    with pytest.raises(OutputPathError, match='is a file, not a folder'):
        check_output(tmp_path / 'file' / 'sub' / 'out', '--out')
    (tmp_path / 'bag').mkdir()
    with pytest.raises(OutputPathError, match=r'already exists \(pass --overwrite'):
        check_output(tmp_path / 'bag', 'OUT_BAG', exists_ok=False, overwrite_flag='--overwrite')
    with pytest.raises(OutputPathError, match=r'must not end in \.bag.*use .*/x$'):
        check_output(tmp_path / 'x.bag', '--record', bag=True)
    assert check_output(tmp_path / 'new' / 'deep' / 'out', '--out') == tmp_path / 'new' / 'deep' / 'out'
    assert not (tmp_path / 'new').exists()  # the check creates nothing


def test_read_only_file_system_is_reported(tmp_path, monkeypatch):
    def read_only(*args, **kwargs):
        raise OSError(errno.EROFS, 'Read-only file system')

    monkeypatch.setattr(tempfile, 'mkstemp', read_only)
    with pytest.raises(OutputPathError, match=r'cannot write in .*: Read-only file system'):
        check_output(tmp_path / 'out', '--out')


@pytest.mark.parametrize(
    'argv',
    [
        ['demo', '--out', '{f}/out'],
        ['evaluate', '{d}', '--out', '{f}/out', '--methods', 'single_view'],
        ['convert', '{d}', '{f}/out'],
        ['run', '--bag', '{d}', '--record', '{f}/out'],
    ],
    ids=['demo', 'evaluate', 'convert', 'run'],
)
def test_every_command_checks_its_output_first(argv, tmp_path, capsys):
    blocker = tmp_path / 'a_file'
    blocker.write_text('x')
    line = one_line_error(capsys, [a.format(f=blocker, d=tmp_path) for a in argv])
    assert f'{blocker} is a file, not a folder' in line


@pytest.mark.parametrize(
    ('argv', 'existing'),
    [
        (['adapt', '{d}/no_sequence', '--out', '{d}/a.pt'], 'a.pt'),
        (['export', '--format', 'torchscript', '--out', '{d}/m.pt'], 'm.pt'),
        (['train', '{d}', '--out', '{d}/run', '--ship', '{d}/s.pt'], 's.pt'),
        (['train', '{d}', '--out', '{d}/run', '--ship', '{d}/s.pt'], 's.yaml'),
        (['run', '--bag', '{d}', '--save-map', '{d}/map.ply'], 'map.ply'),
    ],
    ids=['adapt', 'export', 'train-ship', 'train-ship-yaml', 'run-save-map'],
)
def test_an_output_already_there_is_kept_unless_overwrite_is_given(argv, existing, tmp_path, capsys):
    """A checkpoint, an exported model (or a shipped one's YAML) or a map from an earlier run is a
    result: it is refused before any work (adapt's sequence is not even looked for), naming
    --overwrite, and left as it was."""
    kept = tmp_path / existing
    kept.write_text('an earlier result')
    line = one_line_error(capsys, [a.format(d=tmp_path) for a in argv])
    assert f'{kept} already exists (pass --overwrite to replace it)' in line
    assert kept.read_text() == 'an earlier result'


def test_overwrite_replaces_and_is_refused_where_nothing_would_be_replaced(tmp_path, capsys):
    model = tmp_path / 'm.pt'
    model.write_text('old')
    assert main(['export', '--format', 'torchscript', '--out', str(model), '--overwrite']) == 0
    assert model.stat().st_size > 1000 and model.with_suffix('.yaml').is_file()
    # (another format of the same stem writing m.yaml again: test_singleview_hosts' `exported`)
    other = tmp_path / 'other.pt'
    other.with_suffix('.yaml').write_text('input_width: 64')  # another model's YAML is kept
    line = one_line_error(capsys, ['export', '--out', str(other)])
    assert line.endswith(
        'other.yaml already exists and describes another model (pass --overwrite to replace it)'
    )
    assert not other.exists() and other.with_suffix('.yaml').read_text() == 'input_width: 64'
    line = one_line_error(capsys, ['run', '--bag', str(tmp_path), '--overwrite'])
    assert line.endswith('--overwrite applies to --save-map, which is not given')
    line = one_line_error(capsys, ['train', str(tmp_path), '--out', str(tmp_path / 'run'), '--overwrite'])
    assert line.endswith('--overwrite applies to --ship, which is not given')
    (tmp_path / 'run').mkdir()
    line = one_line_error(capsys, ['train', str(tmp_path), '--out', str(tmp_path / 'run'), '--resume'])
    assert 'last.pt does not exist' in line


def test_an_earlier_runs_unfinished_recording_is_kept(tmp_path, capsys):
    """A run that failed leaves its recording in OUT.partial; a run again with the same
    --record removed it (with a warning) and so lost it. Now the run refuses before any node
    starts, and the folder is as it was."""
    unfinished = tmp_path / 'out.partial' / 'out'
    unfinished.mkdir(parents=True)
    (unfinished / 'out_0.mcap').write_bytes(b'what the failed run recorded')
    line = one_line_error(capsys, ['run', '--bag', str(tmp_path), '--record', str(tmp_path / 'out')])
    assert line.endswith(
        f'{tmp_path / "out.partial"} holds the unfinished recording of an earlier run: move it away or '
        'remove it, or choose another output'
    )
    assert (unfinished / 'out_0.mcap').read_bytes() == b'what the failed run recorded'


def test_bag_outputs_refuse_the_bag_suffix(tmp_path, capsys):
    assert 'use ' in one_line_error(capsys, ['convert', str(tmp_path), str(tmp_path / 'x.bag')])
    line = one_line_error(capsys, ['run', '--bag', str(tmp_path), '--record', str(tmp_path / 'o.bag')])
    assert 'must not end in .bag' in line


# --- --set and --frames -------------------------------------------------------------------------


def test_unknown_node_and_parameter_have_did_you_mean():
    with pytest.raises(ValueError, match=r"unknown node 'nosuchnode'"):
        check_node_overrides({'nosuchnode': {'x': 1}})
    with pytest.raises(ValueError, match=r"no parameter 'keyframe_evry'; did you mean keyframe_every"):
        check_node_overrides({'multi_view_node': {'keyframe_evry': 3}})
    with pytest.raises(ValueError, match=r"unknown node 'multi_veiw_node'; did you mean multi_view_node"):
        check_node_overrides({'multi_veiw_node': {'keyframe_every': 3}})
    check_node_overrides(
        {
            'multi_view_node': {'keyframe_every': 3, 'use_sim_time': True, 'multi_view.patch': 3},
            'bag_replayer': {'loop': True},
            'fusion_node': {'fusion.compile_kernel': False},
        }
    )


def test_unknown_evaluation_stage_and_key():
    with pytest.raises(ValueError, match=r"unknown stage 'fusoin'; did you mean fusion"):
        check_stage_overrides({'fusoin': {'mode': 'fast'}})
    with pytest.raises(ValueError, match=r"fusion has no parameter 'sigma_1'; did you mean sigma1"):
        check_stage_overrides({'fusion': {'sigma_1': 10}})
    check_stage_overrides({'fusion': {'mode': 'fast', 'stage1_fraction': 0.3}, 'recorded': {'bag': 'x'}})


def test_every_stage_an_evaluation_method_reads_can_be_set():
    """``--set consistency.candidates=all`` (docs/fusion.md, stage 3) was refused as an unknown
    stage: the check's table missed a stage a method reads. Every ``ctx.stage_params(X)`` in
    the evaluation code must be a stage ``evaluate --set`` accepts."""
    import importlib
    import re
    from pathlib import Path

    import depth_fusion_ros.evaluation as evaluation
    from depth_fusion_ros.cli.overrides import evaluation_stages

    root = Path(evaluation.__file__).parent
    read: set[str] = set()
    for path in root.rglob('*.py'):
        source = path.read_text()
        module = importlib.import_module(
            'depth_fusion_ros.' + '.'.join(path.relative_to(root.parent).with_suffix('').parts)
        )
        for arg in re.findall(r'stage_params\(([^)]+)\)', source):
            arg = arg.strip()
            if arg.startswith("'"):
                read.add(arg.strip("'"))
            elif arg.isidentifier() and isinstance(getattr(module, arg, None), str):
                read.add(getattr(module, arg))
    assert {'consistency', 'fusion', 'guard', 'recorded'} <= read
    assert read <= set(evaluation_stages())
    check_stage_overrides({'consistency': {'candidates': 'all', 'enabled': True}})
    with pytest.raises(ValueError, match=r"consistency has no parameter 'tolerence'; did you mean tolerance"):
        check_stage_overrides({'consistency': {'tolerence': 0.1}})


def test_set_typo_is_an_error_in_the_cli(tmp_path, capsys):
    line = one_line_error(capsys, ['run', '--bag', str(tmp_path), '--set', 'multi_view_node.keyframe_evry=3'])
    assert 'did you mean keyframe_every' in line
    line = one_line_error(capsys, ['evaluate', str(tmp_path), '--set', 'fusion.mdoe=fast'])
    assert 'did you mean mode' in line


def test_an_unknown_or_empty_evaluation_method_is_a_sentence_before_the_model_loads(tmp_path, capsys, caplog):
    line = one_line_error(capsys, ['evaluate', str(tmp_path), '--methods', 'fused,fuzed'])
    assert line.startswith("depth-fusion evaluate: error: unknown evaluation method 'fuzed'; available: ")
    assert 'single-view model' not in caplog.text  # refused before any model or data loads
    line = one_line_error(capsys, ['evaluate', str(tmp_path), '--methods', ' , '])
    assert line == "depth-fusion evaluate: error: --methods ' , ' names no method (see --list)"


def test_a_typo_in_a_params_file_section_of_ours_is_an_error_and_other_sections_are_left_alone(
    tmp_path, capsys
):
    """``run --params``: the nodes would only warn about a name they do not declare (and run the
    default), so the CLI refuses it first. A ``/**`` section and a section for another package's
    node hold what they like; the packaged file passes."""
    params = tmp_path / 'params.yaml'
    params.write_text(
        '/**:\n  ros__parameters:\n    use_sim_time: true\n    fusion:\n      mode: exact\n'
        'some_driver_node:\n  ros__parameters:\n    exposure: 3\n'
        'multi_view_node:\n  ros__parameters:\n    keyframe_evry: 3\n    qos_overrides:\n'
        '      /x:\n        publisher:\n          depth: 3\n'
    )
    line = one_line_error(capsys, ['run', '--bag', str(tmp_path), '--params', str(params)])
    assert f"--params {params}: multi_view_node has no parameter 'keyframe_evry'" in line
    assert 'did you mean keyframe_every' in line
    params.write_text(params.read_text().replace('keyframe_evry', 'keyframe_every'))
    check_params_file(params)
    check_params_file(CONFIG)


def test_bench_refuses_a_section_it_does_not_have_instead_of_measuring_nothing(capsys):
    """``bench --only fusoin`` once printed "not available" and exited 0 with no figure."""
    line = one_line_error(capsys, ['bench', '--only', 'fusoin'])
    assert '--only fusoin: no such bench section; did you mean fusion?' in line
    assert 'names no section' in one_line_error(capsys, ['bench', '--only', ','])
    assert '--repeats must be at least 1, got 0' in one_line_error(
        capsys, ['bench', '--only', 'fusion', '--repeats', '0']
    )


@pytest.mark.parametrize('command', [['evaluate', 'x'], ['demo'], ['convert', 'a', 'b'], ['synth', 'o']])
@pytest.mark.parametrize('value', ['0', '-3'])
def test_frames_must_be_positive_and_the_message_names_the_option(command, value, capsys):
    line = one_line_error(capsys, [*command, '--frames', value], code=2)
    assert line.endswith(f'argument --frames: must be at least 1, got {value}')
    assert 'max_frames' not in line


@pytest.mark.parametrize(
    ('argv', 'option', 'minimum'),
    [
        (['adapt', 'x', '--out', 'a.pt', '--stride'], '--stride', 1),
        (['adapt', 'x', '--out', 'a.pt', '--frames'], '--frames', 1),
        (['adapt', 'x', '--out', 'a.pt', '--threads'], '--threads', 0),
        (['adapt', 'x', '--out', 'a.pt', '--neighbours'], '--neighbours', 1),
        (['evaluate', 'x', '--neighbours'], '--neighbours', 1),
        (['evaluate', 'x', '--width'], '--width', 16),
        (['adapt', 'x', '--out', 'a.pt', '--height'], '--height', 16),
        (['train', 'x', '--out', 't.pt', '--every'], '--every', 1),
        (['train', 'x', '--out', 't.pt', '--steps'], '--steps', 1),
        (['train', 'x', '--out', 't.pt', '--threads'], '--threads', 1),
    ],
)
def test_counts_below_their_meaning_are_refused_not_read_as_a_default(argv, option, minimum, capsys):
    """``adapt --stride 0`` and ``train --every 0`` once ran as stride 1, ``evaluate --width 7``
    scored a 7-pixel-wide image and ``--neighbours 0`` failed only after the data loaded."""
    line = one_line_error(capsys, [*argv, str(minimum - 1)], code=2)
    assert line.endswith(f'argument {option}: must be at least {minimum}, got {minimum - 1}')


# --- a bag lacking a needed topic -------------------------------------------------------------


def test_missing_inputs_are_named():
    opts = RunOptions(bag=Path('b'))
    assert missing_inputs(opts, ALL) == []
    assert missing_inputs(opts, [t for t in ALL if t != '/camera/pose']) == ['the pose topic /camera/pose']
    no_info = [t for t in ALL if 'camera_info' not in t]
    assert 'camera_info' in missing_inputs(opts, no_info)[0]
    with_k = RunOptions(
        bag=Path('b'), overrides={'multi_view_node': {'camera_intrinsics': [500, 500, 320, 240]}}
    )
    assert missing_inputs(with_k, no_info) == []
    compressed = ['/camera/rgb/image_color/compressed', *ALL[1:]]
    assert missing_inputs(opts, compressed) == []
    remapped = RunOptions(bag=Path('b'), overrides={'bag_replayer': {'remap': ['/odom_pose:=/camera/pose']}})
    assert missing_inputs(remapped, [*ALL[:2], '/odom_pose']) == []
    only_images = RunOptions(
        bag=Path('b'), overrides={'bag_replayer': {'topics': ['/camera/rgb/image_color']}}
    )
    assert len(missing_inputs(only_images, ALL)) == 2


def test_missing_pose_stops_before_start_or_runs_with_allow_missing(caplog):
    topics = [t for t in ALL if t != '/camera/pose']
    with pytest.raises(MissingInputError, match=r'lacks the pose topic /camera/pose .*--allow-missing'):
        check_inputs(RunOptions(bag=Path('b')), topics)
    assert check_inputs(RunOptions(bag=Path('b'), allow_missing=True), topics) == [
        'the pose topic /camera/pose'
    ]
    assert 'running without the pose topic' in caplog.text


def test_a_bag_posed_only_on_tf_is_sent_to_convert():
    """A robot's bag whose poses are only on /tf: the nodes cannot subscribe to it (tf2_msgs is
    not on pip), so the missing pose topic says how to get one."""
    topics = [*(t for t in ALL if t != '/camera/pose'), '/tf', '/tf_static']
    (said,) = missing_inputs(RunOptions(bag=Path('b')), topics)
    assert said.startswith('the pose topic /camera/pose (its poses are on /tf')
    assert 'depth-fusion convert BAG OUT --tf-world-frame FRAME' in said


def test_run_on_a_bag_without_pose_is_one_line(synthetic_tum_dir, tmp_path, capsys):
    from run_bags import shifted_copy, small_bag

    bag = shifted_copy(
        small_bag(synthetic_tum_dir, tmp_path / 'full', frames=3), tmp_path / 'nopose', 0, ('/camera/pose',)
    )
    line = one_line_error(capsys, ['run', '--bag', str(bag), '--record', str(tmp_path / 'out')])
    assert re.search(r'lacks the pose topic /camera/pose \(it has: .*image_color', line), line
    assert not (tmp_path / 'out').exists() and not (tmp_path / 'out.partial').exists()


_NOT_A_NAME = 'is not a valid ROS topic name (topic name'


@pytest.mark.parametrize(
    ('argv', 'said'),
    [
        (
            ['launch', '--pose', 'bad//topic'],
            f"--pose 'bad//topic' {_NOT_A_NAME} must not contain repeated '/')",
        ),
        (['launch', '--image', '1abc'], f"--image '1abc' {_NOT_A_NAME} token must not start with a number)"),
        (['launch', '--camera-info', ''], f"--camera-info '' {_NOT_A_NAME} must not be empty string)"),
        (
            ['run', '--bag', 'b', '--record', 'o', '--record-topic', '/a/'],
            f"--record-topic '/a/' {_NOT_A_NAME} must not end with a forward slash)",
        ),
        (
            ['run', '--bag', 'b', '--record-topic', '/rosout'],
            '--record-topic /rosout: nothing records it without --record OUT_BAG',
        ),
    ],
)
def test_topic_names_are_checked_before_any_node_starts(argv, said, capsys, tmp_path, monkeypatch):
    """A name rcl refuses once reached the forked node as a remap and ended in its traceback
    after the graph had started; an empty ``--pose ''`` was taken as no option at all."""
    monkeypatch.chdir(tmp_path)
    assert one_line_error(capsys, argv) == f'depth-fusion {argv[0]}: error: {said}'


def test_a_record_topic_the_bag_holds_nothing_of_is_said():
    """``--record-topic`` of a name the graph never published was left out of the bag in silence."""
    from depth_fusion_ros.cli.run import unrecorded_topics
    from depth_fusion_ros.nodes.graph.options import RunResult

    result = RunResult(
        announced=[], fused=[], missing={}, recorded=None, seconds=1.0,
        counts={'/a': 3, '/quiet': 0}, unannounced=['/typo'],
    )  # fmt: skip
    assert unrecorded_topics(result, ['/a', '/typo', '/quiet', '/typo']) == [
        '--record-topic /typo: nothing recorded (no node of the graph published it)',
        '--record-topic /quiet: nothing recorded (its publisher sent nothing)',
    ]


# --- pinned dependencies ----------------------------------------------------------------------


def test_every_venv_requirement_is_pinned():
    text = (ROOT / 'scripts' / 'venv.sh').read_text()
    block = text[text.index('REQUIREMENTS=(') : text.index(')', text.index('REQUIREMENTS=('))]
    reqs = re.findall(r'"([^"]+)"', block)
    assert len(reqs) >= 14
    assert all(re.fullmatch(r'[A-Za-z0-9_.\-]+==[0-9][0-9A-Za-z.+]*', r) for r in reqs), reqs


def test_building_the_parser_imports_neither_torch_nor_the_renderer():
    """``depth-fusion --help`` (and every command, before it runs) builds all the parsers: the
    ``export`` and ``synth`` ones once imported torch and the synthetic renderer (scipy) for
    their choices, 4.7 s before anything happened (0.4 s now)."""
    import subprocess
    import sys

    code = (
        'import sys\n'
        'from depth_fusion_ros.cli.main import build_parser\n'
        'parser = build_parser()\n'
        'names = ("torch", "scipy", "onnxruntime", "depth_fusion_ros.data.synthetic.render")\n'
        'heavy = sorted(m for m in names if m in sys.modules)\n'
        'print(heavy)\n'
        'from depth_fusion_ros.data.synthetic import SynthConfig, render_sequence\n'
        'print(SynthConfig.__name__, render_sequence.__name__)\n'
    )
    out = subprocess.run([sys.executable, '-c', code], capture_output=True, text=True, check=True).stdout
    assert out.splitlines() == ['[]', 'SynthConfig render_sequence'], out


def _help_examples() -> list[str]:
    """Every ``depth-fusion ...`` example line of the top-level help and of each command's
    description and epilog (continuation backslashes joined, comments cut)."""
    import argparse

    from depth_fusion_ros.cli.main import build_parser

    parser = build_parser()
    subs = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    texts = [parser.description or ''] + [
        t or '' for p in subs.choices.values() for t in (p.description, p.epilog)
    ]
    lines = []
    for text in texts:
        for line in re.sub(r'\\\n\s*', ' ', text).splitlines():
            if line.strip().startswith('depth-fusion '):
                lines.append(re.split(r'\s+#', line.strip())[0])
    return lines


def test_every_example_in_the_help_is_a_command_line_the_cli_accepts():
    """The help's examples are what a new user types first: each parses, and none names a
    rosbag2 output the command refuses (the top-level help once said `convert ... room.bag`)."""
    import shlex

    from depth_fusion_ros.cli.main import build_parser

    examples = _help_examples()
    assert len(examples) >= 30, examples
    parser = build_parser()
    for line in examples:
        try:
            args = parser.parse_args(shlex.split(line)[1:])
        except SystemExit:
            pytest.fail(f'the help example does not parse: {line}')
        outputs = [args.out] if args.command == 'convert' else []
        outputs += [getattr(args, 'record', None)] if args.command == 'run' else []
        for out in filter(None, outputs):
            assert not str(out).endswith('.bag'), f'a rosbag2 output named .bag in the help: {line}'


def test_every_command_line_in_the_readme_and_docs_code_blocks_parses():
    """The fenced shell blocks of README.md and docs/ are copied as they are: each
    ``depth-fusion`` line in them parses (``[...]``, an optional part, is left out)."""
    import shlex

    from depth_fusion_ros.cli.main import build_parser

    parser = build_parser()
    checked = 0
    for doc in [ROOT / 'README.md', *sorted((ROOT / 'docs').glob('*.md'))]:
        # Every fence pairs with its own close (a ```python block must not shift the pairing
        # and turn the prose after it into a "block"); shell and untagged blocks are checked.
        for language, block in re.findall(r'```([\w-]*)\n(.*?)```', doc.read_text(), re.S):
            if language not in ('', 'bash', 'sh', 'console'):
                continue
            for line in re.sub(r'\\\n\s*', ' ', block).splitlines():
                line = line.strip().removeprefix('$ ')
                if not line.startswith('depth-fusion '):
                    continue
                line = re.split(r'\s+#|\s+\||\s+>|\s+&&|\s+2>', line)[0]
                optional = line
                while (inner := re.sub(r'\[[^\[\]]*\]', '', optional)) != optional:  # [a [b]]: inner first
                    optional = inner
                try:
                    parser.parse_args(shlex.split(optional)[1:])
                except SystemExit:
                    pytest.fail(f'{doc.name}: the command line does not parse: {line}')
                checked += 1
    assert checked >= 15, checked
