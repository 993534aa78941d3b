"""The one exception for bad user input: its message is one line, shown to the user as is."""


class UserError(ValueError):
    """Bad input from the user: an option, a file, a folder. The CLI prints it in one line (exit 2).

    Internal bugs are never UserErrors, so they keep their traceback.
    """
