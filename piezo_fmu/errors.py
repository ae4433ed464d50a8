"""Errors that are the user's to fix: the CLI prints them as one line and exits with status 2."""


class UserError(Exception):
    """Bad input (a file, an option, a parameter): the message says what and where, and what to do."""
