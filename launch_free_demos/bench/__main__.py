"""``python -m launch_free_demos.bench [NAME] [args]`` (``./dev bench``): one benchmark by name,
or the full suite without one; ``--list`` (or ``help``) lists them. Arguments after NAME are the
benchmark's own (``./dev bench NAME --help``)."""
import importlib
import sys

#: NAME -> (module of this package, what it measures); the suite runs without a NAME.
BENCHMARKS = {
    'foundation': ('foundation', 'codec and demo backend timings, next to one memcpy'),
    'transport': ('transport', 'cross-process latency: stock rclpy, our CPU path, demo backend'),
    'record': ('record', 'recording 4K at 30 Hz: buffer_record vs a stock rclpy recorder, vs dd'),
    'mixed': ('mixed', 'CPU per frame beside a legacy listener (demo publisher, 4K, 10 Hz)'),
    'bringup': ('bringup', "a new subscriber's wait for zero-copy (demo publisher, 1080p, 30 Hz)"),
    'hotpath': ('hotpath', "one message's time, stage by stage, on both sides"),
    'bare': ('bare', 'our per-message Python: stock rclpy, the bare descriptor path, demo'),
    'churn': ('churn', 'subscribers coming and going: what the steady ones get, ours vs stock'),
    'lane': ('lane', "a steady demo publisher's publish(), its lane and full path, vs stock"),
    'wakeup': ('wakeup', "one executor wake-up of a node with several topics, ours vs stock"),
    'cuda': ('cuda', 'GPU frames between processes: cuda backend vs D2H + stock + H2D (a GPU)'),
}
SUITE = ('suite', 'the full suite, table and plot (default; --quick for a shorter one)')


def listing() -> str:
    rows = [('(none)', SUITE[1])] + [(name, about) for name, (_, about) in BENCHMARKS.items()]
    return 'usage: ./dev bench [NAME] [args]\n\n' + '\n'.join(
        f'  {name:<11} {about}' for name, about in rows)


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    if argv and argv[0] in ('--list', 'help'):
        print(listing())
        return 0
    name = argv.pop(0) if argv and not argv[0].startswith('-') else None
    if name is not None and name not in BENCHMARKS:
        print(f'bench: unknown benchmark {name!r}\n\n{listing()}', file=sys.stderr)
        return 2
    module = importlib.import_module(f'{__package__}.{(BENCHMARKS[name] if name else SUITE)[0]}')
    sys.argv = [f'./dev bench {name or ""}'.rstrip(), *argv]  # argparse's prog: "dev bench NAME"
    return module.main(argv) or 0


if __name__ == '__main__':
    sys.exit(main())
