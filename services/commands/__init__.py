"""The ``slamlens`` program and the commands that compose the services (no service of their
own): the dispatcher (``cli``) and its command table (``registry``), the generated reference
(``reference``), the router, certificates, launch, demo, figures, status and register."""
