/* virtual_arduino: an ATmega328P at 16 MHz in simavr behind a pseudo-terminal.
 *
 *   virtual_arduino [--pace] [--log FILE] [--eeprom FILE] [--eeprom-stuck] [--bootloader HEX]
 *                   [FIRMWARE.hex|.elf]
 *
 * Prints "PTY <path>" on stdout once the UART is reachable (pyserial can open it at any baud),
 * and logs every edge of D8 (PB0, trigger), D9 (PB1, scene servo) and D10 (PB2, turntable) to
 * the log file as "<simulated time in us, 4 decimals> <pin> <0|1> <host CLOCK_MONOTONIC ns>",
 * plus "<t> RESET" lines.
 * --pace keeps simulated time at or behind the wall clock (needed by avrdude's bootloader
 * timeouts); without it the chip runs as fast as the host allows.  --eeprom loads the EEPROM
 * from FILE at start (if it exists) and writes it back on SIGTERM / SIGINT / SIGHUP, or when
 * the process that started the harness dies.  FILE is checked before the chip starts: an
 * existing FILE must be a readable, writable 1024-byte image, a new one needs a writable
 * folder; otherwise the harness exits with status 2 and a message naming FILE, so settings
 * are never silently lost.  The image is written atomically (temp file, then rename); a failed
 * write is reported on stderr with exit status 1.  --eeprom-stuck is a fault for tests: EEPROM
 * writes do not stick (a worn-out chip).  --bootloader loads a bootloader hex at its own address
 * and starts there (BOOTRST), like a real Uno.
 * Facts and simavr 1.6 pitfalls handled here: ../shared/notes/firmware.md.
 */
#define _GNU_SOURCE
#include <errno.h>
#include <fcntl.h>
#include <libgen.h>
#include <pty.h>
#include <sys/stat.h>
#include <termios.h>
#include <signal.h>
#include <stdio.h>
#include <stdlib.h>
#include <string.h>
#include <time.h>
#include <unistd.h>

#include <simavr/avr_eeprom.h>
#include <simavr/avr_ioport.h>
#include <simavr/avr_uart.h>
#include <simavr/sim_avr.h>
#include <simavr/sim_elf.h>
#include <simavr/sim_hex.h>

#define FREQ 16000000UL
#define EEPROM_SIZE 1024

static avr_t *avr;
static FILE *logf;
static int pace;
static const char *eeprom_path;
static int eeprom_stuck;
static pid_t parent_pid;
static volatile sig_atomic_t stop_requested;
static struct timespec wall0;
static void (*core_reset)(avr_t *);

static void log_time(void)
{
    unsigned long long c = avr->cycle;
    fprintf(logf, "%llu.%04llu", c / 16, (c % 16) * 625);
}

static void pin_changed(avr_irq_t *irq, uint32_t value, void *param)
{
    struct timespec now;
    (void)irq;
    if (!logf)
        return;
    /* the host's CLOCK_MONOTONIC when the edge was simulated: where the closed-loop virtual
     * rig places it in physical time (the chip may run slower than real time under load) */
    clock_gettime(CLOCK_MONOTONIC, &now);
    log_time();
    fprintf(logf, " %s %u %lld\n", (const char *)param, value ? 1u : 0u,
            (long long)now.tv_sec * 1000000000LL + now.tv_nsec);
}

/* The UART bridge.  simavr 1.6's uart_pty part stalls for good when more than 511 bytes
 * arrive before the firmware answers (its thread waits for output that never comes), its
 * input waits for an XON that interrupt-driven firmware never triggers, and its stop never
 * returns; so the harness bridges the pty itself, from the simulation thread: every tick it
 * reads what the host wrote (non-blocking) and feeds the UART until the UART signals XOFF
 * (its input FIFO is full); what the firmware sends is written to the pty at once, and
 * dropped, like on a real USB-serial bridge, when no host has the port open. */
static int pty_master = -1;
static char pty_name[256];
static uint8_t host_buf[4096];
static size_t host_len, host_done;
static volatile int uart_full;
static avr_irq_t *uart_in, *uart_xoff;

static void uart_output(avr_irq_t *irq, uint32_t value, void *param)
{
    uint8_t b = (uint8_t)value;
    (void)irq;
    (void)param;
    if (write(pty_master, &b, 1) != 1) {
        /* no host, or its buffer is full: the byte is lost, as on the wire */
    }
}

static void uart_xoff_hook(avr_irq_t *irq, uint32_t value, void *param)
{
    (void)irq;
    (void)param;
    if (value)
        uart_full = 1;
}

static int pty_open(void)
{
    struct termios tio;
    int slave;
    if (openpty(&pty_master, &slave, pty_name, NULL, NULL) < 0)
        return -1;
    tcgetattr(pty_master, &tio);
    cfmakeraw(&tio);
    tcsetattr(pty_master, TCSANOW, &tio);
    close(slave);      /* the host opens it; until then reads fail with EIO: no input */
    fcntl(pty_master, F_SETFL, fcntl(pty_master, F_GETFL) | O_NONBLOCK);
    return 0;
}

static void pty_pump(void)
{
    if (host_done == host_len) {
        ssize_t r = read(pty_master, host_buf, sizeof(host_buf));
        host_len = r > 0 ? (size_t)r : 0;
        host_done = 0;
    }
    uart_xoff->value = 0;   /* so that the next "FIFO full" is notified */
    uart_full = 0;
    while (host_done < host_len && !uart_full)
        avr_raise_irq(uart_in, host_buf[host_done++]);
}

#define TICK_US 250

/* every TICK_US of simulated time: bridge the UART, flush the log, pace */
static avr_cycle_count_t tick(avr_t *a, avr_cycle_count_t when, void *param)
{
    static unsigned n;
    (void)param;
    pty_pump();
    if (logf && ++n % 4 == 0)
        fflush(logf);
    if (n % 400 == 0 && getppid() != parent_pid)
        stop_requested = 1;        /* our parent died (even by SIGKILL): save and exit */
    if (pace) {
        struct timespec now;
        double wall, sim;
        clock_gettime(CLOCK_MONOTONIC, &now);
        wall = (double)(now.tv_sec - wall0.tv_sec) + 1e-9 * (double)(now.tv_nsec - wall0.tv_nsec);
        sim = (double)a->cycle / (double)FREQ;
        if (sim > wall)
            usleep((useconds_t)((sim - wall) * 1e6));
    }
    return when + FREQ / 1000000 * TICK_US;
}

static void on_reset(avr_t *a)
{
    if (core_reset)
        core_reset(a);
    /* a reset wipes the cycle timers: register ours again */
    avr_cycle_timer_register(a, FREQ / 1000000 * TICK_US, tick, NULL);
    if (logf) {
        log_time();
        fprintf(logf, " RESET\n");
    }
}

static void on_signal(int sig)
{
    (void)sig;
    stop_requested = 1;
}

static int load_hex(const char *path, int is_boot)
{
    ihex_chunk_p chunks = NULL;
    int n = read_ihex_chunks(path, &chunks), i;
    if (n <= 0) {
        fprintf(stderr, "virtual_arduino: %s: cannot read Intel hex\n", path);
        return -1;
    }
    for (i = 0; i < n; i++) {
        if (chunks[i].baseaddr + chunks[i].size > avr->flashend + 1) {
            fprintf(stderr, "virtual_arduino: %s: data beyond the 32 KiB flash\n", path);
            return -1;
        }
        memcpy(avr->flash + chunks[i].baseaddr, chunks[i].data, chunks[i].size);
    }
    if (is_boot) {
        avr->reset_pc = chunks[0].baseaddr;    /* BOOTRST: start in the bootloader */
        avr->pc = chunks[0].baseaddr;
    }
    free_ihex_chunks(chunks);
    return 0;
}

/* Checks --eeprom before the chip starts (exit status 2, FILE named): an existing image must
 * be a regular, readable and writable file of exactly EEPROM_SIZE bytes; a new one needs an
 * existing, writable folder (the image is written there through a temp file). */
static int eeprom_check(const char *path)
{
    struct stat st;
    char dir_buf[4096];
    const char *dir;
    int fd;
    if (strlen(path) >= sizeof(dir_buf)) {
        fprintf(stderr, "virtual_arduino: %s: path too long\n", path);
        return -1;
    }
    strcpy(dir_buf, path);
    dir = dirname(dir_buf);
    if (stat(dir, &st) != 0 || !S_ISDIR(st.st_mode)) {
        fprintf(stderr, "virtual_arduino: %s: EEPROM image folder %s does not exist; create it "
                        "or choose another --eeprom path\n", path, dir);
        return -1;
    }
    if (access(dir, W_OK | X_OK) != 0) {
        fprintf(stderr, "virtual_arduino: %s: EEPROM image folder %s is not writable (%s); the "
                        "settings could not be saved; choose another --eeprom path\n",
                path, dir, strerror(errno));
        return -1;
    }
    if (stat(path, &st) != 0) {
        if (errno == ENOENT)
            return 0;              /* first run: the chip's EEPROM is erased (0xFF) */
        fprintf(stderr, "virtual_arduino: %s: %s\n", path, strerror(errno));
        return -1;
    }
    if (!S_ISREG(st.st_mode)) {
        fprintf(stderr, "virtual_arduino: %s: not a regular file; give an EEPROM image file "
                        "path for --eeprom\n", path);
        return -1;
    }
    fd = open(path, O_RDWR);
    if (fd < 0) {
        fprintf(stderr, "virtual_arduino: %s: EEPROM image not readable and writable (%s); fix "
                        "its permissions or choose another --eeprom path\n", path, strerror(errno));
        return -1;
    }
    close(fd);
    if (st.st_size != EEPROM_SIZE) {
        fprintf(stderr, "virtual_arduino: %s: EEPROM image is %lld bytes, expected %d (corrupt or "
                        "not an ATmega328P image); move it away to start with an erased EEPROM\n",
                path, (long long)st.st_size, EEPROM_SIZE);
        return -1;
    }
    return 0;
}

static int eeprom_load(void)
{
    uint8_t buf[EEPROM_SIZE];
    avr_eeprom_desc_t d = {.ee = buf, .offset = 0, .size = EEPROM_SIZE};
    FILE *f = fopen(eeprom_path, "rb");
    size_t n;
    if (!f) {
        if (errno == ENOENT)
            return 0;
        fprintf(stderr, "virtual_arduino: %s: cannot read the EEPROM image: %s\n", eeprom_path,
                strerror(errno));
        return -1;
    }
    n = fread(buf, 1, EEPROM_SIZE, f);
    fclose(f);
    if (n != EEPROM_SIZE) {
        fprintf(stderr, "virtual_arduino: %s: EEPROM image shorter than %d bytes (it changed "
                        "while starting?)\n", eeprom_path, EEPROM_SIZE);
        return -1;
    }
    avr_ioctl(avr, AVR_IOCTL_EEPROM_SET, &d);
    return 0;
}

/* Written to a temp file in the same folder, then renamed: a crash mid-write never leaves a
 * truncated image.  Returns -1 (message on stderr) when the image could not be saved. */
static int eeprom_save(void)
{
    uint8_t buf[EEPROM_SIZE];
    avr_eeprom_desc_t d = {.ee = buf, .offset = 0, .size = EEPROM_SIZE};
    char tmp[4200];
    int fd, ok;
    avr_ioctl(avr, AVR_IOCTL_EEPROM_GET, &d);
    snprintf(tmp, sizeof(tmp), "%s.tmp-%ld", eeprom_path, (long)getpid());
    fd = open(tmp, O_WRONLY | O_CREAT | O_TRUNC, 0644);
    ok = fd >= 0 && write(fd, buf, EEPROM_SIZE) == EEPROM_SIZE && fsync(fd) == 0;
    if (fd >= 0 && close(fd) != 0)
        ok = 0;
    if (ok && rename(tmp, eeprom_path) == 0)
        return 0;
    fprintf(stderr, "virtual_arduino: %s: cannot save the EEPROM image: %s; the settings of "
                    "this run are lost\n", eeprom_path, strerror(errno));
    unlink(tmp);
    return -1;
}

/* --eeprom-stuck: every write the firmware makes is undone right after simavr performed it
 * (simavr calls the EECR writers in the order they registered, its EEPROM module first). */
static uint8_t stuck_image[EEPROM_SIZE];

static void eeprom_stuck_hook(avr_t *a, avr_io_addr_t addr, uint8_t v, void *param)
{
    avr_eeprom_desc_t d = {.ee = NULL, .offset = 0, .size = 0};
    uint16_t ee_addr = (uint16_t)(a->data[0x41] | (a->data[0x42] << 8));
    (void)addr;
    (void)param;
    if (!(v & 0x02) || ee_addr >= EEPROM_SIZE)          /* EEPE: a write was requested */
        return;
    avr_ioctl(a, AVR_IOCTL_EEPROM_GET, &d);
    if (d.ee)
        d.ee[ee_addr] = stuck_image[ee_addr];
}

static void eeprom_stuck_init(void)
{
    avr_eeprom_desc_t d = {.ee = stuck_image, .offset = 0, .size = EEPROM_SIZE};
    avr_ioctl(avr, AVR_IOCTL_EEPROM_GET, &d);
    avr_register_io_write(avr, 0x3F, eeprom_stuck_hook, NULL);    /* EECR */
}

int main(int argc, char **argv)
{
    const char *fw = NULL, *boot = NULL, *log_path = NULL;
    static const char *names[3] = {"D8", "D9", "D10"};
    int i, status;

    for (i = 1; i < argc; i++) {
        if (!strcmp(argv[i], "--pace"))
            pace = 1;
        else if (!strcmp(argv[i], "--log") && i + 1 < argc)
            log_path = argv[++i];
        else if (!strcmp(argv[i], "--eeprom") && i + 1 < argc)
            eeprom_path = argv[++i];
        else if (!strcmp(argv[i], "--eeprom-stuck"))
            eeprom_stuck = 1;
        else if (!strcmp(argv[i], "--bootloader") && i + 1 < argc)
            boot = argv[++i];
        else if (argv[i][0] != '-' && !fw)
            fw = argv[i];
        else {
            fprintf(stderr, "usage: %s [--pace] [--log FILE] [--eeprom FILE] [--eeprom-stuck] "
                            "[--bootloader HEX] [FIRMWARE.hex|.elf]\n", argv[0]);
            return 2;
        }
    }
    if (!fw && !boot) {
        fprintf(stderr, "virtual_arduino: give a firmware and/or --bootloader\n");
        return 2;
    }
    if (eeprom_path && eeprom_check(eeprom_path) != 0)
        return 2;
    parent_pid = getppid();

    if (fw && strlen(fw) > 4 && !strcmp(fw + strlen(fw) - 4, ".elf")) {
        elf_firmware_t f;
        memset(&f, 0, sizeof(f));
        if (elf_read_firmware(fw, &f) != 0) {
            fprintf(stderr, "virtual_arduino: %s: cannot read ELF\n", fw);
            return 1;
        }
        strcpy(f.mmcu, "atmega328p");
        f.frequency = FREQ;
        avr = avr_make_mcu_by_name(f.mmcu);
        if (!avr || avr_init(avr) != 0)
            return 1;
        avr_load_firmware(avr, &f);
    } else {
        avr = avr_make_mcu_by_name("atmega328p");
        if (!avr || avr_init(avr) != 0)
            return 1;
        avr->frequency = FREQ;
        if (fw && load_hex(fw, 0) != 0)
            return 1;
    }
    avr->frequency = FREQ;
    if (boot && load_hex(boot, 1) != 0)
        return 1;
    avr->log = 0;

    if (log_path) {
        logf = fopen(log_path, "w");
        if (!logf) {
            fprintf(stderr, "virtual_arduino: cannot write %s: %s\n", log_path, strerror(errno));
            return 1;
        }
    }
    for (i = 0; i < 3; i++)
        avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_IOPORT_GETIRQ('B'), i), pin_changed,
                                (void *)names[i]);
    if (eeprom_path && eeprom_load() != 0)
        return 2;
    if (eeprom_stuck)
        eeprom_stuck_init();

    core_reset = avr->reset;
    avr->reset = on_reset;
    avr_cycle_timer_register(avr, FREQ / 1000000 * TICK_US, tick, NULL);

    {
        uint32_t flags = 0;
        avr_ioctl(avr, AVR_IOCTL_UART_GET_FLAGS('0'), &flags);
        flags &= ~AVR_UART_FLAG_STDIO;       /* binary data: no stdio dump */
        avr_ioctl(avr, AVR_IOCTL_UART_SET_FLAGS('0'), &flags);
    }
    if (pty_open() != 0) {
        fprintf(stderr, "virtual_arduino: cannot open a pseudo-terminal: %s\n", strerror(errno));
        return 1;
    }
    uart_in = avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_INPUT);
    uart_xoff = avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_OUT_XOFF);
    avr_irq_register_notify(avr_io_getirq(avr, AVR_IOCTL_UART_GETIRQ('0'), UART_IRQ_OUTPUT),
                            uart_output, NULL);
    avr_irq_register_notify(uart_xoff, uart_xoff_hook, NULL);
    printf("PTY %s\n", pty_name);
    fflush(stdout);

    signal(SIGTERM, on_signal);
    signal(SIGINT, on_signal);
    signal(SIGHUP, on_signal);
    clock_gettime(CLOCK_MONOTONIC, &wall0);
    while (!stop_requested) {
        int state = avr_run(avr);
        if (state == cpu_Done || state == cpu_Crashed) {
            fprintf(stderr, "virtual_arduino: the chip stopped (state %d)\n", state);
            break;
        }
    }
    status = eeprom_path && eeprom_save() != 0 ? 1 : 0;
    if (logf)
        fclose(logf);
    fflush(stdout);
    fflush(stderr);
    _exit(status);
}
