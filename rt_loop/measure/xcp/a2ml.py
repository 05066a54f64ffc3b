"""The A2ML of the A2L's IF_DATA XCP: how a tool reads the XCP blocks the file carries.

Written here after the structure of ASAM MCD-1 XCP 1.4 (its common part and
its Ethernet transport layers), declaring what ``rt_loop.measure.xcp.a2l``
emits and no more than a tool needs to read it:

* the common parameters: PROTOCOL_LAYER (timeouts, MAX_CTO/MAX_DTO, byte
  order, address granularity, OPTIONAL_CMD and OPTIONAL_LEVEL1_CMD, the block
  modes of COMMUNICATION_MODE_SUPPORTED), SEGMENT (in a MEMORY_SEGMENT: its
  CHECKSUM type and largest block, its pages, their access and init segment),
  PAG and DAQ (dynamic DAQ, the identification field, STIM,
  TIMESTAMP_SUPPORTED, the EVENTs with their direction, cycle and
  consistency);
* the transport layers XCP_ON_UDP_IP and XCP_ON_TCP_IP (version, port and
  HOST_NAME, ADDRESS or IPV6).

Every enum has the values the standard gives its keywords; the command enums
list the standard's codes of every command, not only those the slave
implements, so a new command needs no change here (the codes are checked
against ``protocol.py``'s in tests/test_a2l_tools.py). Optional parts of the
standard the file does not use (DAQ_LIST, PGM, TIME_CORRELATION, CAN and the
other transports, ...) are left out: the A2ML may describe less than the
standard, never differently.

``A2ML``: the text, from ``/begin A2ML`` to ``/end A2ML``; ``block()``: it
indented for a MODULE.
"""

from __future__ import annotations

__all__ = ["A2ML", "OPTIONAL_CMD_CODES", "OPTIONAL_LEVEL1_CMD_CODES", "block"]

#: the XCP commands' codes (the standard's command table): OPTIONAL_CMD's enum
OPTIONAL_CMD_CODES: dict[str, int] = {
    "GET_COMM_MODE_INFO": 0xFB, "GET_ID": 0xFA, "SET_REQUEST": 0xF9, "GET_SEED": 0xF8,
    "UNLOCK": 0xF7, "SET_MTA": 0xF6, "UPLOAD": 0xF5, "SHORT_UPLOAD": 0xF4,
    "BUILD_CHECKSUM": 0xF3, "TRANSPORT_LAYER_CMD": 0xF2, "USER_CMD": 0xF1, "DOWNLOAD": 0xF0,
    "DOWNLOAD_NEXT": 0xEF, "DOWNLOAD_MAX": 0xEE, "SHORT_DOWNLOAD": 0xED, "MODIFY_BITS": 0xEC,
    "SET_CAL_PAGE": 0xEB, "GET_CAL_PAGE": 0xEA, "GET_PAG_PROCESSOR_INFO": 0xE9,
    "GET_SEGMENT_INFO": 0xE8, "GET_PAGE_INFO": 0xE7, "SET_SEGMENT_MODE": 0xE6,
    "GET_SEGMENT_MODE": 0xE5, "COPY_CAL_PAGE": 0xE4, "CLEAR_DAQ_LIST": 0xE3,
    "SET_DAQ_PTR": 0xE2, "WRITE_DAQ": 0xE1, "SET_DAQ_LIST_MODE": 0xE0,
    "GET_DAQ_LIST_MODE": 0xDF, "START_STOP_DAQ_LIST": 0xDE, "START_STOP_SYNCH": 0xDD,
    "GET_DAQ_CLOCK": 0xDC, "READ_DAQ": 0xDB, "GET_DAQ_PROCESSOR_INFO": 0xDA,
    "GET_DAQ_RESOLUTION_INFO": 0xD9, "GET_DAQ_LIST_INFO": 0xD8, "GET_DAQ_EVENT_INFO": 0xD7,
    "FREE_DAQ": 0xD6, "ALLOC_DAQ": 0xD5, "ALLOC_ODT": 0xD4, "ALLOC_ODT_ENTRY": 0xD3,
    "PROGRAM_START": 0xD2, "PROGRAM_CLEAR": 0xD1, "PROGRAM": 0xD0, "PROGRAM_RESET": 0xCF,
    "GET_PGM_PROCESSOR_INFO": 0xCE, "GET_SECTOR_INFO": 0xCD, "PROGRAM_PREPARE": 0xCC,
    "PROGRAM_FORMAT": 0xCB, "PROGRAM_NEXT": 0xCA, "PROGRAM_MAX": 0xC9, "PROGRAM_VERIFY": 0xC8,
    "WRITE_DAQ_MULTIPLE": 0xC7, "TIME_CORRELATION_PROPERTIES": 0xC6,
    "DTO_CTR_PROPERTIES": 0xC5,
}

#: the two-byte commands after LEVEL_1_COMMAND (0xC0): OPTIONAL_LEVEL1_CMD's enum
OPTIONAL_LEVEL1_CMD_CODES: dict[str, int] = {
    "GET_VERSION": 0x00, "SET_DAQ_PACKED_MODE": 0x01, "GET_DAQ_PACKED_MODE": 0x02,
    "SW_DBG_OVER_XCP": 0xFC, "POD_COMMANDS": 0xFD,
}


def _enum(codes: dict[str, int], indent: str) -> str:
    items = [f'{indent}  "{name}" = 0x{code:02X}' for name, code in codes.items()]
    return "enum {\n" + ",\n".join(items) + f"\n{indent}}}"


_TEXT = f"""\
/begin A2ML

  struct Protocol_Layer {{
    uint;                          /* XCP protocol layer version, 0x0104 */
    uint;                          /* T1 [ms] */
    uint;                          /* T2 [ms] */
    uint;                          /* T3 [ms] */
    uint;                          /* T4 [ms] */
    uint;                          /* T5 [ms] */
    uint;                          /* T6 [ms] */
    uint;                          /* T7 [ms] */
    uchar;                         /* MAX_CTO */
    uint;                          /* MAX_DTO */
    enum {{
      "BYTE_ORDER_MSB_LAST" = 0,
      "BYTE_ORDER_MSB_FIRST" = 1
    }};
    enum {{
      "ADDRESS_GRANULARITY_BYTE" = 1,
      "ADDRESS_GRANULARITY_WORD" = 2,
      "ADDRESS_GRANULARITY_DWORD" = 4
    }};
    taggedstruct {{
      ("OPTIONAL_CMD" {_enum(OPTIONAL_CMD_CODES, "      ")})*;
      ("OPTIONAL_LEVEL1_CMD" {_enum(OPTIONAL_LEVEL1_CMD_CODES, "      ")})*;
      "COMMUNICATION_MODE_SUPPORTED" taggedunion {{
        "BLOCK" taggedstruct {{
          "SLAVE";
          "MASTER" struct {{
            uchar;                 /* MAX_BS */
            uchar;                 /* MIN_ST [100 us] */
          }};
        }};
        "INTERLEAVED" uchar;       /* QUEUE_SIZE */
      }};
    }};
  }};

  struct Segment {{
    uchar;                         /* SEGMENT_NUMBER */
    uchar;                         /* number of pages */
    uchar;                         /* ADDRESS_EXTENSION */
    uchar;                         /* COMPRESSION_METHOD */
    uchar;                         /* ENCRYPTION_METHOD */
    taggedstruct {{
      block "CHECKSUM" struct {{
        enum {{
          "XCP_ADD_11" = 1,
          "XCP_ADD_12" = 2,
          "XCP_ADD_14" = 3,
          "XCP_ADD_22" = 4,
          "XCP_ADD_24" = 5,
          "XCP_ADD_44" = 6,
          "XCP_CRC_16" = 7,
          "XCP_CRC_16_CITT" = 8,
          "XCP_CRC_32" = 9,
          "XCP_USER_DEFINED" = 255
        }};
        taggedstruct {{
          "MAX_BLOCK_SIZE" ulong;  /* the largest block of one BUILD_CHECKSUM */
          "EXTERNAL_FUNCTION" char[256];
        }};
      }};
      (block "PAGE" struct {{
        uchar;                     /* PAGE_NUMBER */
        enum {{
          "ECU_ACCESS_NOT_ALLOWED" = 0,
          "ECU_ACCESS_WITHOUT_XCP_ONLY" = 1,
          "ECU_ACCESS_WITH_XCP_ONLY" = 2,
          "ECU_ACCESS_DONT_CARE" = 3
        }};
        enum {{
          "XCP_READ_ACCESS_NOT_ALLOWED" = 0,
          "XCP_READ_ACCESS_WITHOUT_ECU_ONLY" = 1,
          "XCP_READ_ACCESS_WITH_ECU_ONLY" = 2,
          "XCP_READ_ACCESS_DONT_CARE" = 3
        }};
        enum {{
          "XCP_WRITE_ACCESS_NOT_ALLOWED" = 0,
          "XCP_WRITE_ACCESS_WITHOUT_ECU_ONLY" = 1,
          "XCP_WRITE_ACCESS_WITH_ECU_ONLY" = 2,
          "XCP_WRITE_ACCESS_DONT_CARE" = 3
        }};
        taggedstruct {{
          "INIT_SEGMENT" uchar;    /* the segment the page is initialised from */
        }};
      }})*;
      "DEFAULT_PAGE_NUMBER" uchar;
    }};
  }};

  struct Pag {{
    uchar;                         /* MAX_SEGMENTS */
    taggedstruct {{
      "FREEZE_SUPPORTED";
    }};
  }};

  struct Daq {{
    enum {{
      "STATIC" = 0,
      "DYNAMIC" = 1
    }};
    uint;                          /* MAX_DAQ */
    uint;                          /* MAX_EVENT_CHANNEL */
    uchar;                         /* MIN_DAQ */
    enum {{
      "OPTIMISATION_TYPE_DEFAULT" = 0,
      "OPTIMISATION_TYPE_ODT_TYPE_16" = 1,
      "OPTIMISATION_TYPE_ODT_TYPE_32" = 2,
      "OPTIMISATION_TYPE_ODT_TYPE_64" = 3,
      "OPTIMISATION_TYPE_ODT_TYPE_ALIGNMENT" = 4,
      "OPTIMISATION_TYPE_MAX_ENTRY_SIZE" = 5
    }};
    enum {{
      "ADDRESS_EXTENSION_FREE" = 0,
      "ADDRESS_EXTENSION_ODT" = 1,
      "ADDRESS_EXTENSION_DAQ" = 3
    }};
    enum {{
      "IDENTIFICATION_FIELD_TYPE_ABSOLUTE" = 0,
      "IDENTIFICATION_FIELD_TYPE_RELATIVE_BYTE" = 1,
      "IDENTIFICATION_FIELD_TYPE_RELATIVE_WORD" = 2,
      "IDENTIFICATION_FIELD_TYPE_RELATIVE_WORD_ALIGNED" = 3
    }};
    enum {{
      "GRANULARITY_ODT_ENTRY_SIZE_DAQ_BYTE" = 1,
      "GRANULARITY_ODT_ENTRY_SIZE_DAQ_WORD" = 2,
      "GRANULARITY_ODT_ENTRY_SIZE_DAQ_DWORD" = 4,
      "GRANULARITY_ODT_ENTRY_SIZE_DAQ_DLONG" = 8
    }};
    uchar;                         /* MAX_ODT_ENTRY_SIZE_DAQ */
    enum {{
      "NO_OVERLOAD_INDICATION" = 0,
      "OVERLOAD_INDICATION_PID" = 1,
      "OVERLOAD_INDICATION_EVENT" = 2
    }};
    taggedstruct {{
      "PRESCALER_SUPPORTED";
      "RESUME_SUPPORTED";
      "STORE_DAQ_SUPPORTED";
      block "STIM" struct {{
        enum {{
          "GRANULARITY_ODT_ENTRY_SIZE_STIM_BYTE" = 1,
          "GRANULARITY_ODT_ENTRY_SIZE_STIM_WORD" = 2,
          "GRANULARITY_ODT_ENTRY_SIZE_STIM_DWORD" = 4,
          "GRANULARITY_ODT_ENTRY_SIZE_STIM_DLONG" = 8
        }};
        uchar;                     /* MAX_ODT_ENTRY_SIZE_STIM */
        taggedstruct {{
          "BIT_STIM_SUPPORTED";
          "MIN_ST_STIM" uchar;     /* [100 us] */
        }};
      }};
      block "TIMESTAMP_SUPPORTED" struct {{
        uint;                      /* TIMESTAMP_TICKS */
        enum {{
          "NO_TIME_STAMP" = 0,
          "SIZE_BYTE" = 1,
          "SIZE_WORD" = 2,
          "SIZE_DWORD" = 4
        }};
        enum {{
          "UNIT_1NS" = 0,
          "UNIT_10NS" = 1,
          "UNIT_100NS" = 2,
          "UNIT_1US" = 3,
          "UNIT_10US" = 4,
          "UNIT_100US" = 5,
          "UNIT_1MS" = 6,
          "UNIT_10MS" = 7,
          "UNIT_100MS" = 8,
          "UNIT_1S" = 9,
          "UNIT_1PS" = 10,
          "UNIT_10PS" = 11,
          "UNIT_100PS" = 12
        }};
        taggedstruct {{
          "TIMESTAMP_FIXED";
        }};
      }};
      "PID_OFF_SUPPORTED";
      (block "EVENT" struct {{
        char[101];                 /* EVENT_CHANNEL_NAME */
        char[9];                   /* EVENT_CHANNEL_SHORT_NAME */
        uint;                      /* EVENT_CHANNEL_NUMBER */
        enum {{
          "DAQ" = 1,
          "STIM" = 2,
          "DAQ_STIM" = 3
        }};
        uchar;                     /* MAX_DAQ_LIST (0xFF: any number) */
        uchar;                     /* EVENT_CHANNEL_TIME_CYCLE */
        uchar;                     /* EVENT_CHANNEL_TIME_UNIT (as TIMESTAMP's, 0: 1 ns) */
        uchar;                     /* EVENT_CHANNEL_PRIORITY */
        taggedstruct {{
          "CONSISTENCY" enum {{
            "DAQ" = 0,
            "EVENT" = 1
          }};
        }};
      }})*;
    }};
  }};

  taggedstruct Common_Parameters {{
    block "PROTOCOL_LAYER" struct Protocol_Layer;
    block "SEGMENT" struct Segment;
    block "PAG" struct Pag;
    block "DAQ" struct Daq;
  }};

  struct IP_Parameters {{
    uint;                          /* XCP on UDP_IP / TCP_IP version, 0x0104 */
    uint;                          /* PORT */
    taggedunion {{
      "HOST_NAME" char[256];
      "ADDRESS" char[15];
      "IPV6" char[39];
    }};
  }};

  block "IF_DATA" taggedunion if_data {{
    "XCP" struct {{
      taggedstruct Common_Parameters;
      taggedstruct {{
        block "XCP_ON_UDP_IP" struct IP_Parameters;
        block "XCP_ON_TCP_IP" struct IP_Parameters;
      }};
    }};
  }};

/end A2ML"""

#: the A2ML block, from ``/begin A2ML`` to ``/end A2ML``
A2ML: str = _TEXT


def block(indent: str = "    ") -> list[str]:
    """The A2ML's lines, each indented by ``indent`` (blank lines stay blank)."""
    return [indent + line if line else "" for line in A2ML.split("\n")]
