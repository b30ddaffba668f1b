"""Every command README.md and docs/*.md show is run: here, by another named test, or by CI
itself; every Python program they show is run here exactly as printed; every relative link
between them (and CHANGELOG.md) leads to a file, and a heading, that exist; every test they
name (``file::test``) exists.

A command added to a document without a place in COVERAGE fails the first test, and so does a
``python`` block without a test below (each block starts with ``# <name>.py``, a name unique
across the documents), so the documentation cannot rot silently.
"""
import json
import os
import re
import shlex
import signal
import subprocess
import sys
import time
import tomllib
from pathlib import Path

import pytest

from harness.installed import executable, in_dev_venv
from harness.stuck import communicate_all, popen

ROOT = Path(__file__).resolve().parent.parent
#: The documents whose commands and programs are run: README.md, then docs/*.md.
DOCUMENTS = {path.relative_to(ROOT).as_posix(): path.read_text()
             for path in [ROOT / 'README.md', *sorted((ROOT / 'docs').glob('*.md'))]}
#: The documents whose links are checked: those, and the changelog.
LINKED = [*DOCUMENTS, 'CHANGELOG.md']

#: Document command -> where it runs: 'here' (below), a test file that runs it, or 'ci'.
COVERAGE = {
    './dev demo': 'here',
    './dev demo --help': 'here',
    './dev test': 'ci',                                   # .ci/run runs exactly this
    './dev setup': 'here',
    # an offline install (docs/development.md): the wheelhouse made and installed offline; the
    # checkout's install is test_install.py's (run as printed on the GPU machine)
    './dev wheelhouse': 'test_wheelhouse.py',
    './dev wheelhouse --skip-present numpy,setuptools,pytest,pytest-xdist,hypothesis,'
    'matplotlib,wheel': 'test_wheelhouse.py',
    'cd .wheelhouse && python3 -m pip install --no-index --no-deps --no-compile ./*.whl':
        'test_wheelhouse.py',
    'cd rosidl_buffer_py && python3 -m pip install --no-index --no-deps --no-build-isolation -e .':
        'test_install.py',
    './dev bench cuda': 'test_cuda_backend.py',  # where there is no GPU; test_cuda_gpu.py else
    'BUDGET=420 OUT=/tmp/gpu_check bash tools/gpu_check.sh': 'test_wheelhouse.py',  # on a GPU
    './dev bench cuda [--sizes 4k,1080p] [--paths stock,demo,floor,cuda,small] [--frames N] '
    '[--rate HZ]': 'test_cuda_backend.py',
    'python3 -m pytest -n 8 test/': 'ci',  # ./dev test's pytest, on the target's python3
    # README's quick start: the pair of programs, run here as printed
    '.venv/bin/python viewer.py &': 'here',
    '.venv/bin/python camera.py': 'here',
    # the benchmarks (docs/benchmarks.md): each run small and short by the test named
    './dev bench [NAME]': 'test_benchmark.py',          # each NAME below
    './dev bench': 'test_benchmark.py',  # full mode: the quick mode's code, more sizes (20 min)
    './dev bench --quick': 'test_benchmark.py',  # --smoke: the same code, fewest frames
    './dev bench --list': 'here',
    './dev bench foundation': 'here',
    './dev bench transport': 'here',                      # with fewer frames and payloads
    './dev bench transport --payloads "1 KiB" --frames 60 --rate 5 --rounds 8': 'here',  # fewer
    './dev bench transport --payloads "1 KiB" "3840x2160 rgb8" --frames 30 --rate 10 '
    '--rounds 3': 'here',                                 # as its --attribution run
    './dev bench transport --payloads "1 KiB" "3840x2160 rgb8" --frames 30 --rate 10 '
    '--rounds 3 --attribution': 'here',                   # fewer frames, one round
    './dev bench hotpath': 'test_benchmark.py',           # 8 frames at 20 Hz
    './dev bench hotpath --rounds 5': 'test_benchmark.py',  # two rounds of 8 frames
    './dev bench bare': 'test_benchmark.py',              # 8 frames, one round
    './dev bench bare --opcodes': 'test_benchmark.py',    # 8 frames
    './dev bench mixed': 'test_benchmark.py',             # small frames, fewer of them
    # run_latency, the measurement this command prints per run, on the mixed graph
    './dev bench mixed --latency --graphs pure,mixed --payload 640x480 --rate 30 --frames 600':
        'test_mixed_latency.py',
    './dev bench mixed --threads': 'test_benchmark.py',   # two graphs, small frames
    './dev bench mixed --graphs mixed --rounds 2': 'test_benchmark.py',  # one graph of the same
    './dev bench mixed --graphs pure,mixed': 'test_benchmark.py',  # the same two graphs
    # the hotpath benchmark's own module, as the A B rounds of benchmarks.md ran it per tree
    'python -m launch_free_demos.bench.hotpath --frames 40 --rate 10': 'test_benchmark.py',
    './dev bench bringup': 'test_bringup.py',             # small frames, 2 trials
    './dev bench record': 'test_record.py',               # 1 s of small frames
    './dev bench churn': 'test_benchmark.py',             # 4 s of 640x480, 2 busy processes
    './dev bench lane': 'test_benchmark.py',              # 8 frames at 20 Hz, one round
    './dev bench wakeup': 'test_benchmark.py',            # 2 topics, 5 wake-ups, one round
    './dev bench wakeup --topics 8 --rounds 2': 'test_benchmark.py',  # the same, shorter
    # optional, never installed by ./dev setup or CI: test_packaging checks the file against the
    # benchmark's peers, test_benchmark runs each peer where it is installed
    '.venv/bin/pip install -r requirements-bench.txt': 'test_packaging.py',
    '.venv/bin/python test/harness/measure_inspector.py 20': 'here',     # with 1 run instead of 20
    # the harnesses (docs/development.md)
    '.venv/bin/python test/harness/scenarios.py': 'test_transport.py',  # every scenario
    '.venv/bin/python test/harness/equivalence.py [names] [--echo]': 'test_equivalence.py',
    '.venv/bin/python test/harness/attacks.py': 'test_attacks.py',  # 40 frames instead of 300
    './dev stress [SCENARIO...] [--runs N] [--load K]': 'test_equivalence.py',  # one round
    '.venv/bin/python test/harness/first_frame.py --runs 20': 'test_bringup.py',  # 1 run
    # the user guide's nodes and tools
    '.venv/lib/rosidl_buffer_py/image_publisher --ros-args -p backend:=demo -p width:=1920 '
    '-p height:=1080': 'here',
    'buffer_topic_info <topic> [--json] [--wait S] [--probe]': 'test_info.py',
    'buffer_topic_info --probe': 'test_info.py',
    # the recording example, run as one script
    '.venv/lib/rosidl_buffer_py/image_publisher --ros-args -p backend:=demo -p '
    'topic:=/camera/image -p count:=90 -p wait_for_subscribers:=1 &': 'test_record.py',
    '.venv/lib/rosidl_buffer_py/buffer_record /camera/image -o camera_bag --duration 10':
        'test_record.py',
    '.venv/lib/rosidl_buffer_py/buffer_bag_info camera_bag': 'test_record.py',
    '.venv/lib/rosidl_buffer_py/buffer_play camera_bag --rate 2': 'test_record.py',
    'wait': 'test_record.py',
    'buffer_bag_info camera_bag': 'test_record.py',
    'buffer_record [topics ...] [--all]': 'test_record.py',
    'buffer_bag_info <bag> [--json]': 'test_record.py',
    'buffer_play <bag>': 'test_play.py',
    'buffer_bag_reindex <bag>': 'test_reindex.py',
    'colcon build': 'test_colcon.py',
    'colcon test': 'test_colcon.py',
    'colcon test --packages-select rosidl_buffer_py': 'test_colcon.py',
    'colcon test-result --verbose': 'test_colcon.py',
    # "Your own venv": a fresh venv, pip install of a copy of the checkout
    'python3 -m venv myenv': 'test_install.py',
    'myenv/bin/pip install /path/to/rosidl_buffer_py': 'test_install.py',
    'myenv/bin/buffer_bag_info --help': 'test_install.py',
}

#: How an inline command starts (a path alone, without a space, is not a command).
COMMAND_STARTS = ('./dev ', '.venv/', 'buffer_', 'colcon ', 'myenv/', 'python -m', 'python3 ')


def _without_code_blocks(text):
    return re.sub(r'^```.*?^```', '', text, flags=re.S | re.M)


def documented_commands():
    """Every command of the documents: bash blocks line by line, and inline commands."""
    commands = set()
    for text in DOCUMENTS.values():
        for block in re.findall(r'```bash\n(.*?)```', text, re.S):
            for line in block.splitlines():
                line = line.split('#', 1)[0].strip()
                if line:
                    commands.add(line)
        for inline in re.findall(r'`([^`\n]+)`', _without_code_blocks(text)):
            inline = inline.strip()
            if inline.startswith(COMMAND_STARTS) and ' ' in inline:
                commands.add(inline)
    return commands


#: The documents' commands that only make sense in the ./dev checkout (under `colcon test` the
#: source copy has no .venv; those are run by ./dev test).
dev_only = pytest.mark.skipif(not in_dev_venv(), reason='not running in the ./dev venv')


def python_snippets():
    """The documents' ``python`` blocks by the file name on their first line."""
    snippets = {}
    for document, text in DOCUMENTS.items():
        for block in re.findall(r'```python\n(.*?)```', text, re.S):
            match = re.match(r'# (\w+\.py)', block)
            assert match, f'a python block of {document} does not start with "# <name>.py": ' \
                f'{block[:80]!r}'
            assert match.group(1) not in snippets, f'two programs named {match.group(1)}'
            snippets[match.group(1)] = block
    return snippets


def heading_anchors(text):
    """The anchors GitHub gives a markdown text's headings."""
    anchors, seen = set(), {}
    for heading in re.findall(r'^#{1,6} +(.+?) *$', _without_code_blocks(text), re.M):
        slug = re.sub(r'[^\w\- ]', '', heading.lower()).replace(' ', '-')
        anchors.add(f'{slug}-{seen[slug]}' if slug in seen else slug)
        seen[slug] = seen.get(slug, 0) + 1
    return anchors


def relative_links(text):
    """The targets of a markdown text's links that are not URLs (code blocks excluded)."""
    targets = re.findall(r'\[[^\]]*\]\(([^)\s]+)\)', _without_code_blocks(text))
    return [t for t in targets if not re.match(r'[a-z][a-z0-9+.-]*:', t)]


def run(command, timeout):
    return subprocess.run(command, shell=True, cwd=ROOT, capture_output=True, text=True,
                          timeout=timeout)


def test_every_documented_command_has_a_place_that_runs_it():
    commands = documented_commands()
    missing = commands - set(COVERAGE)
    assert not missing, f'commands in README.md or docs/ that no test runs: {sorted(missing)}'
    stale = set(COVERAGE) - commands
    assert not stale, f'COVERAGE names commands no document shows any more: {sorted(stale)}'
    for command, where in COVERAGE.items():
        if where.endswith('.py'):
            assert (ROOT / 'test' / where).is_file(), (command, where)


def test_every_relative_link_leads_to_a_file_and_heading_that_exist():
    broken = []
    for document in LINKED:
        source = ROOT / document
        for target in relative_links(source.read_text()):
            path, _, anchor = target.partition('#')
            destination = (source.parent / path).resolve() if path else source
            if not destination.exists():
                broken.append((document, target, 'no such file'))
            elif anchor and (destination.suffix != '.md' or
                             anchor not in heading_anchors(destination.read_text())):
                broken.append((document, target, 'no such heading'))
    assert not broken, broken


def test_readme_links_every_document_of_docs():
    linked = {(ROOT / path.partition('#')[0]).resolve()
              for path in relative_links(DOCUMENTS['README.md'])}
    unlinked = {path.name for path in (ROOT / 'docs').glob('*.md')} - \
        {path.name for path in linked if path.parent == ROOT / 'docs'}
    assert not unlinked, unlinked
    assert ROOT / 'CHANGELOG.md' in linked


def layout_paths(text: str) -> list:
    """The paths the first column of development.md's layout table names: a path with a
    folder sets the folder for the bare file names after it in the same cell."""
    section = text.split('\n## Layout\n', 1)[1].split('\n## ', 1)[0]
    paths = []
    for line in section.splitlines():
        if not line.startswith('| `'):
            continue
        folder = ''
        for token in re.findall(r'`([^`]+)`', line.split(' | ')[0]):
            if '/' in token.rstrip('/'):
                folder = token if token.endswith('/') else token.rsplit('/', 1)[0] + '/'
                paths.append(token)
            elif token.endswith('/'):
                folder = token
                paths.append(token)
            else:
                paths.append(folder + token)
    return paths


def test_the_layout_table_names_every_module_and_only_what_exists():
    """docs/development.md's layout table cannot drift: every module of the two packages is
    in it, and every path it names exists."""
    named = layout_paths((ROOT / 'docs' / 'development.md').read_text())
    assert 'rosidl_buffer_py/publisher.py' in named and 'rosidl_buffer_py/routes.py' in named
    missing = [path for path in named if not (ROOT / path).exists()]
    assert not missing, f'the layout table names what does not exist: {missing}'
    modules = {f'{package}/{module.name}' for package in ('rosidl_buffer_py',
                                                          'demo_buffer_backend',
                                                          'cuda_buffer_backend')
               for module in (ROOT / package).glob('*.py') if module.name != '__init__.py'}
    unnamed = sorted(modules - set(named))
    assert not unnamed, f'modules the layout table does not name: {unnamed}'


def test_layout_paths_reads_folders_and_bare_names():
    text = ('# x\n## Layout\n| path | what |\n|---|---|\n'
            '| `a/b.py`, `c.py` | `not/this.py` |\n| `d/`, `e.py` | x |\n| `f` | y |\n'
            '## Next\n| `g/h.py` | z |\n')
    assert layout_paths(text) == ['a/b.py', 'a/c.py', 'd/', 'd/e.py', 'f']


def test_every_test_the_documents_name_exists():
    """docs/guarantees.md names the test behind each guarantee as `file::test`: each one is a
    test function of that file."""
    named = [(document, file, test) for document, text in DOCUMENTS.items()
             for file, test in re.findall(r'`(test_\w+\.py)::(test_\w+)`', text)]
    assert len(named) > 20, named  # the guarantees name their tests
    missing = [(document, f'{file}::{test}') for document, file, test in named
               if not (ROOT / 'test' / file).is_file() or
               not re.search(rf'^def {test}\(', (ROOT / 'test' / file).read_text(), re.M)]
    assert not missing, missing


def test_link_checker_finds_what_github_names():
    text = '# Where a message\'s time goes (`./dev bench hotpath`)\n## Limits\n## Limits\n' \
        '```\n# not a heading\n```\n[a](x.md#y) [b](https://e.org/z) [c](#limits-1)\n'
    assert heading_anchors(text) == {'where-a-messages-time-goes-dev-bench-hotpath', 'limits',
                                     'limits-1'}
    assert relative_links(text) == ['x.md#y', '#limits-1']


@dev_only
def test_dev_setup_and_demo():
    assert run('./dev setup', 300).returncode == 0
    help_text = run('./dev demo --help', 60)
    assert help_text.returncode == 0 and '--backend' in help_text.stdout
    demo = run('./dev demo', 180)
    assert demo.returncode == 0, demo.stdout[-2000:] + demo.stderr[-2000:]
    assert "| backends seen by the subscriber | {'demo': 150} |" in demo.stdout
    assert '| duplicates / gaps / checksum failures | 0 / 0 / 0 |' in demo.stdout


@dev_only
def test_dev_setup_says_what_it_does_and_shows_pip_only_when_it_fails(tmp_path):
    """One line per step; pip's own output only on failure (a venv without pip fails)."""
    venv = tmp_path / 'venv'
    subprocess.run([sys.executable, '-m', 'venv', '--without-pip', str(venv)], check=True)
    done = subprocess.run([str(ROOT / 'dev'), 'setup'], cwd=ROOT, capture_output=True,
                          text=True, timeout=120,
                          env=dict(os.environ, ROSIDL_BUFFER_PY_VENV=str(venv)))
    assert done.returncode != 0 and done.stdout == '', done.stdout
    lines = done.stderr.splitlines()
    assert lines[0] == 'dev: installing ROS 2 Jazzy from PyPI and the test tools (about a ' \
        'minute)', lines
    assert 'No module named pip' in done.stderr, done.stderr  # what pip (here: python) said
    assert lines[-1].startswith(f'dev: failed (exit {done.returncode}): {venv}/bin/python -m '
                                'pip install'), lines
    assert not (venv / '.rosidl_buffer_py_stamp').exists()


@dev_only
def test_dev_bench_prints_the_table():
    listed = run('./dev bench --list', 300)
    assert listed.returncode == 0, listed.stderr[-2000:]
    for name in ('foundation', 'transport', 'record', 'mixed', 'bringup', 'hotpath', 'churn'):
        assert f'  {name} ' in listed.stdout, listed.stdout
    bench = run('./dev bench foundation', 300)
    assert bench.returncode == 0, bench.stderr[-2000:]
    assert '| 3840x2160 rgb8 | 24,883,200 |' in bench.stdout
    # the documented rounds commands, with fewer frames and rounds (./dev bench transport
    # alone is the same code with every payload, one round; a command whose --attribution
    # run is documented too runs as that one)
    commands = [c for c in COVERAGE if c.startswith('./dev bench transport --')
                and c + ' --attribution' not in COVERAGE]
    assert len(commands) == 2, commands
    for command in commands:
        transport = run(re.sub(r'--frames \d+', '--frames 4',
                               re.sub(r'--rounds \d+', '--rounds 1', command)), 300)
        assert transport.returncode == 0, transport.stderr[-2000:]
        assert '| 1 KiB |' in transport.stdout, transport.stdout
    assert '| 3840x2160 rgb8 |' in transport.stdout and \
        'demo 3840x2160 / stock 1 KiB p50 per round' in transport.stdout, transport.stdout
    for variant in ('1 KiB: demo, channels on SHM / demo (on UDP) p50 per round',
                    '3840x2160 rgb8: demo, channels on SHM / demo (on UDP) p50 per round',
                    '1 KiB: stock rclpy, 4K fill before / stock rclpy p50 per round',
                    'demo 3840x2160 / stock 1 KiB with a 4K fill before p50 per round'):
        assert variant in transport.stdout, transport.stdout


@dev_only
def test_readme_image_publisher_command_runs_and_stops_cleanly():
    command = [c for c in COVERAGE if c.startswith('.venv/lib/')][0]
    process = subprocess.Popen(shlex.split(command), cwd=ROOT, stdout=subprocess.PIPE,
                               stderr=subprocess.PIPE, text=True, start_new_session=True)
    try:
        time.sleep(4.0)
        os.killpg(process.pid, signal.SIGINT)  # the shell and the node, as Ctrl-C would
        out, err = process.communicate(timeout=30)
    finally:
        if process.poll() is None:
            os.killpg(process.pid, signal.SIGKILL)
            process.wait()
    assert process.returncode == 0, err[-2000:]
    assert 'Traceback' not in err
    report = json.loads(next(line for line in out.splitlines()
                             if line.startswith('REPORT '))[len('REPORT '):])
    assert report['published'] > 0 and report['params']['backend'] == 'demo'


@dev_only
def test_inspector_measurement_command():
    command = [c for c in COVERAGE if 'measure_inspector' in c][0]
    out = run(command.replace(' 20', ' 1'), 120)
    assert out.returncode == 0, out.stdout + out.stderr[-2000:]
    assert 'complete on the first try: 1 of 1' in out.stdout, out.stdout


@dev_only
@pytest.mark.parametrize('name', ['demo_pub_to_legacy_sub'])
def test_scenarios_command_line(name):
    out = run(f'.venv/bin/python test/harness/scenarios.py {name}', 120)
    assert out.returncode == 0, out.stdout + out.stderr[-2000:]
    assert f'| {name} | PASS |' in out.stdout


#: Each program of the documents and the test that runs it as printed.
SNIPPET_TESTS = {
    'camera.py': 'test_camera_and_viewer_exchange_zero_copy_frames',  # and the one below
    'viewer.py': 'test_camera_and_viewer_exchange_zero_copy_frames',
    'points.py': 'test_pointcloud_program',
    'my_backend.py': 'test_backend_guide_module_serves_the_nodes_and_leaves_nothing',
    'gpu_camera.py': 'test_gpu_camera_and_viewer_exchange_zero_copy_tensors',
    'gpu_viewer.py': 'test_gpu_camera_and_viewer_exchange_zero_copy_tensors',
}


def test_every_documented_program_is_run_by_a_test():
    assert set(python_snippets()) == set(SNIPPET_TESTS)
    for test in SNIPPET_TESTS.values():
        assert callable(globals()[test]), test


def _write_snippet(directory, name):
    path = directory / name
    path.write_text(python_snippets()[name])
    return path


def test_camera_and_viewer_exchange_zero_copy_frames(tmp_path):
    """README's quick start programs as a pair: all 30 4K frames arrive as demo Buffers
    (nothing on the main topic)."""
    camera = _write_snippet(tmp_path, 'camera.py')
    viewer = _write_snippet(tmp_path, 'viewer.py')
    processes = [popen([sys.executable, str(viewer)], cwd=tmp_path),
                 popen([sys.executable, str(camera)], cwd=tmp_path)]
    (vcode, vout, verr), (ccode, cout, cerr) = communicate_all(processes, 120)
    assert vcode == 0 and ccode == 0, verr[-2000:] + cerr[-2000:]
    assert vout.strip() == "('DemoBuffer', (2160, 3840, 3), 0) ('DemoBuffer', (2160, 3840, 3), " \
        "29)", vout + verr[-2000:]
    assert 'sent_on_main_topic=0,' in cout, cout  # print(pub.statistics())
    assert cout.splitlines()[-1] == 'True', cout  # the viewer released the last frame


def test_camera_publishes_for_a_plain_subscriber_alone(tmp_path):
    """README's camera with only a plain rclpy subscriber (rviz's case): it does not wait for a
    buffer-aware peer forever, the frames go out as CPU bytes."""
    camera = _write_snippet(tmp_path, 'camera.py')
    # the subscriber stops after 20 s (camera.py waits 5 s for a buffer-aware one first):
    # camera.py's frames are not image_publisher's, whose count it would wait for
    processes = [
        popen([str(executable('legacy_image_subscriber')), '--ros-args', '-p',
                'topic:=/camera/image', '-p', 'timeout_sec:=20']),
        popen([sys.executable, str(camera)], cwd=tmp_path)]
    (scode, sout, serr), (ccode, cout, cerr) = communicate_all(processes, 150)
    assert ccode == 0, cerr[-2000:]
    report = json.loads(next(line for line in sout.splitlines()
                             if line.startswith('REPORT '))[len('REPORT '):])
    # camera.py's frames carry no counter or checksum of image_publisher's: count arrivals
    assert report['received'] > 0 and report['backends'] == {'cpu': report['received']}, \
        (report, serr[-2000:])
    assert 'sent_on_main_topic=0,' not in cout, cout


def test_pointcloud_program(tmp_path):
    code, out, err = communicate_all(
        [popen([sys.executable, str(_write_snippet(tmp_path, 'points.py'))], cwd=tmp_path)],
        120)[0]
    assert code == 0, err[-2000:]
    assert out.strip() == "[('DemoBuffer', (100000, 4))]", out + err[-2000:]


def test_backend_guide_module_serves_the_nodes_and_leaves_nothing(tmp_path):
    """The guide's backend module, registered with the guide's entry point (the TOML block),
    carries image_publisher's frames to image_subscriber; no file of it is left."""
    site = tmp_path / 'site'
    site.mkdir()
    _write_snippet(site, 'my_backend.py')
    [toml] = re.findall(r'```toml\n(.*?)```', DOCUMENTS['docs/backends.md'], re.S)
    entry_points = tomllib.loads(toml)['project']['entry-points']
    dist_info = site / 'my_backend-0.1.dist-info'
    dist_info.mkdir()
    (dist_info / 'METADATA').write_text('Metadata-Version: 2.1\nName: my-backend\n'
                                        'Version: 0.1\n')
    (dist_info / 'entry_points.txt').write_text(''.join(
        f'[{group}]\n' + ''.join(f'{name} = {target}\n' for name, target in points.items())
        for group, points in entry_points.items()))
    env = dict(os.environ, PYTHONPATH=os.pathsep.join(
        filter(None, [str(site), os.environ.get('PYTHONPATH')])))
    before = {n for n in os.listdir('/dev/shm') if n.startswith('mymem_')}
    topic = f'/mymem_{os.getpid()}'
    processes = [
        popen([str(executable('image_subscriber')), '--ros-args', '-p', f'topic:={topic}',
                '-p', 'acceptable_buffer_backends:=mymem', '-p', 'expected_backend:=mymem',
                '-p', 'expected_count:=20', '-p', 'timeout_sec:=60', '-p', 'depth:=20'], env=env),
        popen([str(executable('image_publisher')), '--ros-args', '-p', f'topic:={topic}',
                '-p', 'backend:=mymem', '-p', 'count:=20', '-p', 'rate_hz:=20',
                '-p', 'width:=640', '-p', 'height:=480', '-p', 'depth:=20',
                '-p', 'wait_for_subscribers:=1', '-p', 'wait_for_buffer_peers:=1',
                '-p', 'linger_sec:=10'], env=env)]
    (scode, sout, serr), (pcode, pout, perr) = communicate_all(processes, 120)
    assert scode == 0 and pcode == 0, serr[-2000:] + perr[-2000:]
    report = json.loads(sout.split('REPORT ', 1)[1])
    assert report['backends'] == {'mymem': 20} and report['distinct'] == 20, report
    assert report['checksum_failures'] == 0 and report['wrong_backend'] == 0, report
    left = {n for n in os.listdir('/dev/shm') if n.startswith('mymem_')} - before
    assert not left, left


def _gpu_missing() -> str:
    import cuda_buffer_backend
    why = cuda_buffer_backend.unavailable_reason()
    if why:
        return f'needs a CUDA GPU: {why}'
    import importlib.util
    if importlib.util.find_spec('torch') is None:
        return 'needs torch'
    return ''


def test_gpu_camera_and_viewer_exchange_zero_copy_tensors(tmp_path):
    """README's GPU programs as a pair: all 30 4K frames arrive as CudaBuffers, their values
    right (a GPU and torch needed; skipped with the reason elsewhere)."""
    why = _gpu_missing()
    if why:
        pytest.skip(why)
    camera = _write_snippet(tmp_path, 'gpu_camera.py')
    viewer = _write_snippet(tmp_path, 'gpu_viewer.py')
    v = popen([sys.executable, str(viewer)], cwd=tmp_path)
    time.sleep(3)
    c = popen([sys.executable, str(camera)], cwd=tmp_path)
    (vcode, vout, verr), (ccode, _, cerr) = communicate_all([v, c], 120)
    assert vcode == 0 and ccode == 0, verr[-2000:] + cerr[-2000:]
    assert "('CudaBuffer', 'cuda:0', 0) ('CudaBuffer', 'cuda:0', 29)" in vout, vout
