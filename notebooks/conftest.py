"""pytest settings of the notebook run (``pytest --nbmake notebooks``, part of ``make test``).

nbmake gives a kernel nbclient's default 60 s to start and has no option to change it; on
a heavily shared machine starting ipykernel took longer than that (seen at a load average
of 20 on 2 cores), failing a notebook before its first cell ran. nbmake's client is
replaced by one whose kernels get 600 s to start, as cells get 600 s to run
(``--nbmake-timeout=600`` in the Makefile).
"""
import nbmake.nb_run
from nbclient import NotebookClient
from traitlets import Integer


class _PatientNotebookClient(NotebookClient):
    startup_timeout = Integer(600, help="seconds a kernel may take to start").tag(config=True)


nbmake.nb_run.NotebookClient = _PatientNotebookClient
