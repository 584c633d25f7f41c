"""The benchmarks' S3: a moto server on loopback, its address and test keys in the environment, where
botocore (hence s3fs, and every subprocess) finds them. tests/conftest.py's `s3_endpoint` is the suite's."""

import contextlib
import os
from collections.abc import Iterator


@contextlib.contextmanager
def moto_s3() -> Iterator[dict[str, str]]:
    """For the length of the block: a moto S3 server, and the variables that point at it (set in
    os.environ and yielded, for a subprocess's env)."""
    import s3fs
    from moto.server import ThreadedMotoServer

    server = ThreadedMotoServer(ip_address="127.0.0.1", port=0, verbose=False)
    server.start()
    host, port = server.get_host_and_port()
    env = {
        "AWS_ENDPOINT_URL": f"http://{host}:{port}",
        "AWS_ACCESS_KEY_ID": "testing",
        "AWS_SECRET_ACCESS_KEY": "testing",
        "AWS_DEFAULT_REGION": "us-east-1",
    }
    os.environ.update(env)
    s3fs.S3FileSystem.clear_instance_cache()  # none made before may keep another endpoint
    try:
        yield env
    finally:
        server.stop()
