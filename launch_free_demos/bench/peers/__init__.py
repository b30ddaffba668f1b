"""The benchmark's peer transports: iceoryx2 and zenoh nodes that send and check the same frames
as image_publisher / image_subscriber (optional: requirements-bench.txt)."""
