"""The ground floor of the process: what the machine is (:mod:`.machine`). Every other module may
import it; it imports no other module of the project, and nothing here loads torch at import time."""
