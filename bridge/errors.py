"""The one exception type that every quadsr CLI turns into a clear message and a non-zero exit."""


class UserError(Exception):
    """A mistake in the user's input (a file, a flag, a config value): printed without a traceback."""

    def __init__(self, message: str, hint: str | None = None, exit_code: int = 2):
        super().__init__(message)
        self.hint = hint
        self.exit_code = exit_code

    def __reduce__(self):  # pickled whole (hint, exit code) from a worker (identification.target_pool)
        return (self.__class__, (self.args[0] if self.args else "", self.hint, self.exit_code))

    def __str__(self) -> str:
        text = super().__str__()
        return f"{text}\n  hint: {self.hint}" if self.hint else text
