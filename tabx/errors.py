"""`UserError`: an error in the user's input (a file, an option, a value) that the command line
prints as one clear line, without a traceback. Any layer's command may raise it."""


class UserError(Exception):
    """An error in the user's input (file, option, value): printed as one clear line."""


__all__ = ["UserError"]
