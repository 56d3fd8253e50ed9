"""Shared helpers of the interoperability tests: building a Rust example binary once."""

import json
import os
import pathlib
import subprocess

REPO = pathlib.Path(__file__).resolve().parents[2]


def example_binary(package: str, example: str, env_override: str) -> str:
    """The path of `cargo build -p <package> --example <example>` (honouring
    CARGO_TARGET_DIR), or the binary named by the environment variable `env_override`."""
    explicit = os.environ.get(env_override)
    if explicit:
        return explicit
    out = subprocess.run(
        ["cargo", "build", "-q", "-p", package, "--example", example, "--message-format=json"],
        cwd=REPO,
        check=True,
        capture_output=True,
        text=True,
    ).stdout
    for line in out.splitlines():
        msg = json.loads(line)
        if msg.get("reason") == "compiler-artifact" and msg.get("executable") and msg["target"]["name"] == example:
            return msg["executable"]
    raise RuntimeError(f"cargo did not report the {example} executable")
