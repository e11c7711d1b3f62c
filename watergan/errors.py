"""The base of every error that a user's input causes (the CLI prints these without a traceback)."""


class UserInputError(ValueError):
    """Bad input: a missing folder, an unreadable file, an out-of-bounds parameter... The message
    says what is wrong and what to do."""
