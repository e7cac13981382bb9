"""Tokens and lock ids are typed on command lines: none may start with "-" (argparse would take it for an option)."""

from unittest import mock

from cellctl.service.auth import command_line_safe_token


def test_a_token_never_starts_with_a_dash():
    draws = iter(["-starts-with-a-dash", "_fine"])
    with mock.patch("cellctl.service.auth.secrets.token_urlsafe", side_effect=lambda n: next(draws)):
        assert command_line_safe_token(32) == "_fine"
    assert not any(command_line_safe_token(16).startswith("-") for _ in range(2000))
