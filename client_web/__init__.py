"""The phone page (``index.html``, ``js/``, ``css/``, ``assets/``) and the files of its npm
modules that it imports (``node_modules/``, from ``npm ci``). Not Python: a package only so that
the page ships as package data of the wheel; the server finds it with
``importlib.resources.files("client_web")`` (server/transport/routes_client.py)."""
