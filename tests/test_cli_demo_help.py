"""`dobtune demo --help` names the defaults a newcomer needs (issue 33 minor item)."""

from __future__ import annotations

import argparse

from controller.cli import demo


def test_demo_help_names_its_defaults() -> None:
    p = argparse.ArgumentParser(prog="dobtune demo")
    demo.add_arguments(p)
    text = " ".join(p.format_help().split())
    for option, default in [("--port", "8080"), ("--zenoh-port", "7447"),
                            ("--host", "127.0.0.1"), ("--rig-name", "demo")]:
        assert option in text
        assert f"(default: {default})" in text, (option, text)
    assert p.parse_args([]).port == 8080 and p.parse_args([]).zenoh_port == 7447
