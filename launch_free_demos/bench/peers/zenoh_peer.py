"""zenoh_peer: the benchmark's frames over zenoh's Python bindings with shared memory (a peer).

``python -m launch_free_demos.bench.peers.zenoh_peer --role publisher|subscriber --topic KEY
--root_path DIR [image_publisher / image_subscriber parameters]``

Two zenoh peers, linked by a Unix socket in ``root_path`` (the publisher listens, subscribers
connect; multicast scouting off: a run meets no other zenoh session). The publisher allocates
each frame from a shared-memory provider and puts it with the stamp, counter and CRC32 as the
attachment; the subscriber's callback receives it.

What zenoh's Python API allows, and so what this peer does: a shared-memory buffer
(``ZShmMut``) takes only ``bytes`` or ``bytearray`` and has no buffer protocol, so the frame
cannot be written in place: the publisher fills a ``bytearray`` (the camera frame) and copies it
into the buffer, and the subscriber's only way to numpy is ``payload.to_bytes()``, a full copy
("time to a numpy view" includes it).
"""
import json
import os
import sys
import time

import numpy
import zenoh
import zenoh.shm

from launch_free_demos.bench.peers.common import (
    Received, Stop, frame_header, latency_ms, parse_parameters, payload_shape, payload_size,
    pixels, print_report, publish_frames, write_frame)

#: Frames the publisher's shared-memory pool holds (in flight and being freed).
POOL_FRAMES = 4
SOCKET_NAME = 'zenoh.sock'


def open_session(args, listen: bool) -> zenoh.Session:
    config = zenoh.Config()
    config.insert_json5('scouting/multicast/enabled', 'false')
    config.insert_json5('scouting/gossip/enabled', 'false')
    endpoint = json.dumps([f'unixsock-stream/{os.path.join(args.root_path, SOCKET_NAME)}'])
    if listen:
        config.insert_json5('listen/endpoints', endpoint)
    else:  # subscribers start first: keep retrying until the publisher listens
        config.insert_json5('listen/endpoints', '[]')
        config.insert_json5('connect/endpoints', endpoint)
        config.insert_json5('connect/retry', json.dumps(
            {'period_init_ms': 50, 'period_max_ms': 200, 'period_increase_factor': 1.5}))
    config.insert_json5('transport/shared_memory/enabled', 'true')
    return zenoh.open(config)


def publish(args, stop: Stop) -> int:
    nbytes = payload_size(args)
    session = open_session(args, listen=True)
    try:
        publisher = session.declare_publisher(args.topic)
        provider = zenoh.shm.ShmProvider.default_backend(max(nbytes, 4096) * POOL_FRAMES)
        policy = zenoh.shm.BlockOn(zenoh.shm.GarbageCollect())
        source = pixels(nbytes)
        frame = bytearray(nbytes)  # the camera frame: ZShmMut cannot be written through numpy
        frame_view = numpy.frombuffer(frame, dtype=numpy.uint8)

        def send(counter: int) -> None:
            buffer = provider.alloc(nbytes, policy)
            crc = write_frame(frame_view, source, counter)
            buffer[0:nbytes] = frame  # the one copy into shared memory
            publisher.put(buffer, attachment=frame_header(counter, crc))  # stamped just now

        def matched() -> int:  # zenoh tells whether some subscriber matches, not how many
            return args.wait_for_subscribers if publisher.matching_status.matching else 0

        return publish_frames(args, stop, matched, send)
    finally:
        session.close()


def subscribe(args, stop: Stop) -> int:
    shape = payload_shape(args)
    received = Received(args)

    def on_sample(sample: zenoh.Sample) -> None:
        started = time.perf_counter_ns()  # the callback starts
        header = sample.attachment.to_bytes()
        latency = latency_ms(header)
        view = numpy.frombuffer(sample.payload.to_bytes(), dtype=numpy.uint8).reshape(shape)
        view_ns = time.perf_counter_ns() - started
        shared = sample.payload.as_shm() is not None  # else zenoh fell back to a copy
        received.frame(header, latency, view_ns, view, 'zenoh shm' if shared else 'zenoh')

    session = open_session(args, listen=False)
    try:
        subscriber = session.declare_subscriber(args.topic, on_sample)
        period = args.report_period_sec or 0.25
        while not received.done() and not stop.requested:
            time.sleep(period)
            if args.report_period_sec:
                received.log_progress()
        subscriber.undeclare()
        print_report(received.report())
    finally:
        session.close()
    return 0


def main(argv=None) -> int:
    args = parse_parameters('zenoh_peer', argv, extra=(
        ('--root_path', 'directory of the Unix socket that links the run\'s peers'),))
    stop = Stop()
    return publish(args, stop) if args.role == 'publisher' else subscribe(args, stop)


if __name__ == '__main__':
    sys.exit(main())
