"""buffer_bag_info: what ``ros2 bag info`` prints, for the MCAP bags of :mod:`.record`.

Files, size, storage, duration, start and end, message count, and per topic its type, count
and serialization format. Reads only each file's summary section (no message data), so it is
instant for any bag size. A bag is a directory (``buffer_record -o``) or one ``.mcap`` file.

Usage: ``buffer_bag_info <bag> [--json]``; also ``python -m rosidl_buffer_py.tools.bag_info``.
"""
import argparse
import datetime
import json
import sys
from typing import List, Optional

from rosidl_buffer_py.tools.bag import BagError, BagReader, STORAGE_ID, format_size

__all__ = ['format_info', 'info', 'main']

EXIT_USAGE = 2


def _time(ns: int) -> str:
    stamp = datetime.datetime.fromtimestamp(ns // 1_000_000_000)
    return f'{stamp:%b %d %Y %H:%M:%S}.{ns % 1_000_000_000:09d} ({ns // 1_000_000_000}.' \
           f'{ns % 1_000_000_000:09d})'


def info(bag: BagReader) -> dict:
    """The bag's facts as a dict (what ``--json`` prints)."""
    start, end = bag.time_range()
    return {
        'files': [str(f.path) for f in bag.files],
        'size': bag.size,
        'storage_id': STORAGE_ID,
        'ros_distro': bag.ros_distro,
        'duration_ns': end - start,
        'start_ns': start,
        'end_ns': end,
        'message_count': bag.message_count,
        'topics': [dict(entry, offered_qos_profiles=entry['offered_qos_profiles'])
                   for entry in bag.topics.values()],
    }


def format_info(facts: dict) -> str:
    """``ros2 bag info``'s layout."""
    label = '{:<19}'.format
    lines = [label('Files:') + ('\n' + label('')).join(
                 p.rsplit('/', 1)[-1] for p in facts['files']),
             label('Bag size:') + format_size(facts['size']),
             label('Storage id:') + facts['storage_id'],
             label('ROS Distro:') + (facts['ros_distro'] or 'unknown'),
             label('Duration:') + f'{facts["duration_ns"] / 1e9:.9f}s']
    if facts['message_count']:
        lines += [label('Start:') + _time(facts['start_ns']),
                  label('End:') + _time(facts['end_ns'])]
    lines.append(label('Messages:') + str(facts['message_count']))
    topics = [f'Topic: {t["name"]} | Type: {t["type"]} | Count: {t["count"]} | '
              f'Serialization Format: {t["serialization_format"]}' for t in facts['topics']]
    lines.append(label('Topic information:') + ('\n' + label('')).join(topics))
    return '\n'.join(lines)


def main(argv: Optional[List[str]] = None) -> int:
    parser = argparse.ArgumentParser(prog='buffer_bag_info',
                                     description='Print what a recorded MCAP bag holds.')
    parser.add_argument('bag', help='bag directory or .mcap file')
    parser.add_argument('--json', action='store_true', help='print one JSON object')
    args = parser.parse_args(argv)
    try:
        facts = info(BagReader(args.bag))
    except BagError as exc:
        print(f'buffer_bag_info: error: {exc}', file=sys.stderr)
        return EXIT_USAGE
    print(json.dumps(facts, sort_keys=True) if args.json else format_info(facts))
    return 0


if __name__ == '__main__':
    raise SystemExit(main())
