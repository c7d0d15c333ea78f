//! The restaurant: the whole game state of one episode as a plain `Copy` value, the 57 actions
//! (docs/rules.md §4), one tick of time (§5), the observation (§6) and the action mask (§7).
//!
//! Nothing here draws random numbers: arrivals come from the episode's arrival list, so a copy of
//! a `Restaurant` is a complete future, which the expert's look-ahead relies on. Fixed-size arrays
//! only: a step allocates nothing.

use serde::{Deserialize, Serialize};
use serde_big_array::BigArray;

use super::config::{Config, MAX_ARRIVALS};

/// Number of tables.
pub const NUM_TABLES: usize = 6;
/// Seats of table 1 .. table 6.
pub const TABLE_CAPACITIES: [u8; NUM_TABLES] = [4, 4, 2, 6, 4, 4];
/// Most groups that wait in the queue.
pub const QUEUE_CAPACITY: usize = 7;
/// Food counter slots at the kitchen pass.
pub const NUM_COUNTERS: usize = 5;
/// Items the waiter can carry.
pub const HAND_CAPACITY: usize = 2;
/// Length of the observation vector.
pub const OBSERVATION_SIZE: usize = 40;
/// Number of discrete actions.
pub const NUM_ACTIONS: usize = 57;
/// Room for pending kitchen orders. At most one order per table can be pending (a table orders
/// again only after its food was served or the group ran away, which drops its order), so six
/// would do; the spare slots make that an argument rather than a crash.
const ORDER_CAPACITY: usize = 8;
/// The longest episode, in ticks, even without a time limit (a game without patience decay
/// never ends by itself). Far beyond any real episode; it keeps the clock far from overflowing
/// and gives a restored clock a bound that stepping respects.
pub const MAX_EPISODE_TICKS: u32 = 1 << 30;

/// One observation: 40 small integers (docs/rules.md §6).
pub type Observation = [i8; OBSERVATION_SIZE];
/// One action mask: `true` where the action's preconditions hold (docs/rules.md §7).
pub type ActionMask = [bool; NUM_ACTIONS];

/// Action 0: let time pass.
pub const WAIT: u8 = 0;
/// Action 7: hand the orders in hand to the kitchen.
pub const HAND_IN_ORDERS: u8 = 7;
/// Action 14: drop the dishes in hand at the wash point.
pub const DROP_DISHES: u8 = 14;
const FIRST_GO_TO: u8 = 1;
const FIRST_PICK_UP: u8 = 8;
const FIRST_SEAT: u8 = 15;

/// Table status codes of docs/rules.md §1.
pub mod status {
    /// Free and clean.
    pub const FREE: u8 = 0;
    /// The seated group reads the menu.
    pub const READING: u8 = 1;
    /// The seated group waits for the waiter to take its order.
    pub const READY_TO_ORDER: u8 = 2;
    /// The order was taken; the group waits for its food.
    pub const WAITING_FOR_FOOD: u8 = 3;
    /// The group eats.
    pub const EATING: u8 = 4;
    /// The group left; its dishes are on the table.
    pub const DISHES: u8 = 5;
    /// The group waits for the bill.
    pub const WAITING_FOR_BILL: u8 = 6;
}

/// An item in the waiter's hands, encoded as in the observation: `t` is `order(t)`, `6 + t` is
/// `food(t)`, `12 + t` is `dish(t)`; 0 is an empty hand.
type Item = u8;
const EMPTY: Item = 0;
const fn order(t: u8) -> Item {
    t
}
const fn food(t: u8) -> Item {
    6 + t
}
const fn dish(t: u8) -> Item {
    12 + t
}
/// The table an item belongs to.
const fn table_of(item: Item) -> u8 {
    (item - 1) % 6 + 1
}

/// A group of customers, waiting or seated.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
pub struct Group {
    /// Customer type, 1 or 2: sets the initial patience and its decay.
    pub customer_type: u8,
    /// Number of customers, 1..=6: must fit the table's capacity.
    pub size: u8,
    /// Patience `P`: the group leaves when it reaches 0.
    pub patience: i32,
    /// Grace buffer `B`: used up before patience decays.
    pub buffer: i32,
}

impl Group {
    /// A group as it arrives: full patience and a buffer of 100.
    fn arriving(customer_type: u8, size: u8, config: &Config) -> Group {
        Group {
            customer_type,
            size,
            patience: config.patience[usize::from(customer_type - 1)] as i32,
            buffer: 100,
        }
    }

    /// One tick of impatience; returns whether the group has run out of patience.
    fn decay(&mut self, config: &Config) -> bool {
        // Customer types are 1 and 2; the mask keeps the index in bounds for the empty group that
        // a free table holds, whose decay is computed and thrown away (see `advance`).
        let d = config.decay[usize::from(self.customer_type.wrapping_sub(1) & 1)] as i32;
        let buffer = self.buffer - d;
        // The overshoot is not carried into P (docs/rules.md §5.1). Written as selects, not a
        // branch: the server decays thousands of unrelated groups in a row, so no pattern
        // predicts it.
        self.patience -= if buffer < 0 { d } else { 0 };
        self.buffer = buffer.max(0);
        self.patience <= 0
    }

    /// `P div 200`, as the observation shows it.
    fn patience_level(&self) -> i8 {
        (self.patience / 200) as i8
    }
}

/// One table.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
struct Table {
    /// Status code (see [`status`]).
    status: u8,
    /// The seated group; meaningful in statuses 1, 2, 3, 4 and 6.
    group: Group,
    /// Tick at which reading (status 1) or eating (status 4) started.
    since: u32,
}

impl Table {
    fn is_seated(&self) -> bool {
        (self.status != status::FREE) & (self.status != status::DISHES)
    }
}

/// Bit `t` of `FITS[size]`: table `t + 1` seats a group of `size`.
const FITS: [u8; 7] = {
    let mut fits = [0u8; 7];
    let mut size = 0;
    while size < 7 {
        let mut t = 0;
        while t < NUM_TABLES {
            if size as u8 <= TABLE_CAPACITIES[t] {
                fits[size] |= 1 << t;
            }
            t += 1;
        }
        size += 1;
    }
    fits
};

/// `SPREAD[bits]`: the six low bits of `bits` as six flags, the mask entries of seating one group
/// at tables 1..=6.
const SPREAD: [[bool; NUM_TABLES]; 64] = {
    let mut spread = [[false; NUM_TABLES]; 64];
    let mut bits = 0;
    while bits < 64 {
        let mut t = 0;
        while t < NUM_TABLES {
            spread[bits][t] = bits >> t & 1 == 1;
            t += 1;
        }
        bits += 1;
    }
    spread
};

/// An order handed to the kitchen.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
struct Order {
    /// Table 1..=6.
    table: u8,
    /// Tick at which it was handed in.
    placed: u32,
}

/// What one step did.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub struct StepOutcome {
    /// Change of the score over the whole step.
    pub reward: i64,
    /// `lost >= lives` after the step.
    pub terminated: bool,
    /// The configured time limit was reached.
    pub truncated: bool,
}

/// Score shaping of the expert's look-ahead (docs/rules.md §8); never applied to the real game.
fn shaped_bonus(patience: i32, divisor: i32) -> i64 {
    if patience >= 700 {
        return 0;
    }
    let n = 700 - patience;
    let (q, r) = (n / divisor, n % divisor);
    // round-half-to-even of n / divisor, n > 0 (CPython's `round`).
    let up = 2 * r > divisor || (2 * r == divisor && q % 2 == 1);
    i64::from(q + i32::from(up))
}

/// The complete state of one episode.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct Restaurant {
    /// The numbers of this game.
    config: Config,
    /// The clock: ticks since reset.
    now: u32,
    /// Total score of the episode.
    score: i64,
    /// Groups lost (left the queue or ran away from a table).
    lost: u32,
    /// An arrival happens at the first tick greater than this.
    next_arrival: u32,
    /// Groups that have arrived since reset; the next one is `arrivals[arrived % arrivals_len]`.
    arrived: u32,
    /// The episode's arrival list, `(type, size)` packed as `type << 4 | size`.
    #[serde(with = "BigArray")]
    arrivals: [u8; MAX_ARRIVALS],
    /// Entries of `arrivals` in use, 1..=200.
    arrivals_len: u8,
    /// Waiting groups, oldest first.
    queue: [Group; QUEUE_CAPACITY],
    /// Groups in `queue`.
    queue_len: u8,
    /// Tables 1..=6.
    tables: [Table; NUM_TABLES],
    /// Counter slots: 0 empty, else the table whose food lies there.
    counters: [u8; NUM_COUNTERS],
    /// Items in hand, in pick-up order; empty slots at the end.
    hands: [Item; HAND_CAPACITY],
    /// Orders in the kitchen, oldest first.
    orders: [Order; ORDER_CAPACITY],
    /// Entries of `orders` in use.
    orders_len: u8,
}

/// Why a restored state is not one the game can reach.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("inconsistent game state: {0}")]
pub struct StateError(pub &'static str);

/// An arrival list entry out of range.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
pub enum ArrivalError {
    /// The list is empty or longer than [`MAX_ARRIVALS`].
    #[error("an arrival list must hold 1..=200 groups, got {0}")]
    Length(usize),
    /// A group's type or size is out of range.
    #[error(
        "arrival {index}: customer_type must be in 1..=2 and size in 1..=6, got type {customer_type}, size {size}"
    )]
    Group {
        /// Position in the list.
        index: usize,
        /// The type given.
        customer_type: u32,
        /// The size given.
        size: u32,
    },
}

/// Checks an explicit arrival list and packs it.
pub(crate) fn pack_arrivals(list: &[(u32, u32)]) -> Result<([u8; MAX_ARRIVALS], u8), ArrivalError> {
    if list.is_empty() || list.len() > MAX_ARRIVALS {
        return Err(ArrivalError::Length(list.len()));
    }
    let mut packed = [0u8; MAX_ARRIVALS];
    for (index, &(customer_type, size)) in list.iter().enumerate() {
        if !(1..=2).contains(&customer_type) || !(1..=6).contains(&size) {
            return Err(ArrivalError::Group {
                index,
                customer_type,
                size,
            });
        }
        packed[index] = (customer_type << 4 | size) as u8;
    }
    Ok((packed, list.len() as u8))
}

impl Restaurant {
    /// A freshly reset restaurant (docs/rules.md §3) for the given packed arrival list; the first
    /// group arrives at once.
    pub(crate) fn new(config: Config, arrivals: [u8; MAX_ARRIVALS], arrivals_len: u8) -> Self {
        let mut r = Restaurant {
            config,
            now: 0,
            score: 0,
            lost: 0,
            next_arrival: 0,
            arrived: 0,
            arrivals,
            arrivals_len,
            queue: [Group::default(); QUEUE_CAPACITY],
            queue_len: 0,
            tables: [Table::default(); NUM_TABLES],
            counters: [0; NUM_COUNTERS],
            hands: [EMPTY; HAND_CAPACITY],
            orders: [Order::default(); ORDER_CAPACITY],
            orders_len: 0,
        };
        r.arrive();
        r
    }

    /// The configuration of this episode.
    pub fn config(&self) -> &Config {
        &self.config
    }

    /// Ticks since reset.
    pub fn tick(&self) -> u32 {
        self.now
    }

    /// Total score of the episode so far.
    pub fn score(&self) -> i64 {
        self.score
    }

    /// Groups lost so far.
    pub fn lost(&self) -> u32 {
        self.lost
    }

    /// Whether the episode has ended by losing groups.
    pub fn is_terminated(&self) -> bool {
        self.lost >= self.config.lives
    }

    /// Whether the configured time limit, or the longest episode any game allows
    /// ([`MAX_EPISODE_TICKS`]), has been reached.
    pub fn is_truncated(&self) -> bool {
        (self.config.time_limit != 0 && self.now >= self.config.time_limit)
            || self.now >= MAX_EPISODE_TICKS
    }

    /// The episode's arrival list as `(type, size)` pairs.
    pub fn arrivals(&self) -> impl Iterator<Item = (u8, u8)> + '_ {
        self.arrivals[..usize::from(self.arrivals_len)]
            .iter()
            .map(|&a| (a >> 4, a & 0x0f))
    }

    /// Status code of table `t` (1-based).
    pub fn table_status(&self, t: usize) -> u8 {
        self.tables[t - 1].status
    }

    /// The group seated at table `t` (1-based), if any.
    pub fn seated_group(&self, t: usize) -> Option<&Group> {
        let table = &self.tables[t - 1];
        table.is_seated().then_some(&table.group)
    }

    /// The waiting groups, oldest first.
    pub fn queue(&self) -> &[Group] {
        &self.queue[..usize::from(self.queue_len)]
    }

    /// Counter slots: 0 empty, else the table whose food lies there.
    pub fn counters(&self) -> &[u8; NUM_COUNTERS] {
        &self.counters
    }

    /// The items in hand, encoded as in the observation (0 = empty).
    pub fn hands(&self) -> &[u8; HAND_CAPACITY] {
        &self.hands
    }

    /// Pending kitchen orders as `(table, tick placed)`, oldest first.
    pub fn pending_orders(&self) -> impl Iterator<Item = (u8, u32)> + '_ {
        self.orders[..usize::from(self.orders_len)]
            .iter()
            .map(|o| (o.table, o.placed))
    }

    /// One step: the action, then one tick of time. `action` must be below [`NUM_ACTIONS`]
    /// (larger values are treated as waiting; [`super::Game::step`] refuses them).
    pub fn step(&mut self, action: u8) -> StepOutcome {
        let before = self.score;
        self.apply::<false>(action);
        self.advance();
        StepOutcome {
            reward: self.score - before,
            terminated: self.is_terminated(),
            truncated: self.is_truncated(),
        }
    }

    /// A copy of this restaurant in which the groups still to arrive are `future` (in order,
    /// then repeating) instead of the rest of the episode's arrival list: everything a player can
    /// see (tables, queue, counters, hands, clock) is unchanged. A planner simulates such copies,
    /// with futures drawn from its own generator, so that it never reads the hidden list.
    pub fn with_future_arrivals(&self, future: &[(u8, u8)]) -> Result<Restaurant, ArrivalError> {
        if future.is_empty() || future.len() > MAX_ARRIVALS {
            return Err(ArrivalError::Length(future.len()));
        }
        let mut copy = *self;
        for (index, &(customer_type, size)) in future.iter().enumerate() {
            if !(1..=2).contains(&customer_type) || !(1..=6).contains(&size) {
                return Err(ArrivalError::Group {
                    index,
                    customer_type: u32::from(customer_type),
                    size: u32::from(size),
                });
            }
            copy.arrivals[index] = customer_type << 4 | size;
        }
        // The rest of the real list must not survive in the copy, even where it is never read.
        copy.arrivals[future.len()..].fill(0);
        copy.arrivals_len = future.len() as u8;
        copy.arrived = 0;
        Ok(copy)
    }

    /// The expert's look-ahead: the score change of one step with the shaping of docs/rules.md §8.
    pub(crate) fn shaped_step_gain(&self, action: u8) -> i64 {
        let mut copy = *self;
        copy.apply::<true>(action);
        copy.advance();
        copy.score - self.score
    }

    fn hands_used(&self) -> usize {
        self.hands.iter().filter(|&&i| i != EMPTY).count()
    }

    fn hold(&mut self, item: Item) {
        if let Some(slot) = self.hands.iter_mut().find(|i| **i == EMPTY) {
            *slot = item;
        }
    }

    /// Removes items from the hands, keeping the others in order.
    fn drop_from_hands(&mut self, mut gone: impl FnMut(Item) -> bool) {
        let mut kept = [EMPTY; HAND_CAPACITY];
        let mut n = 0;
        for &item in &self.hands {
            if item != EMPTY && !gone(item) {
                kept[n] = item;
                n += 1;
            }
        }
        self.hands = kept;
    }

    fn counter_holds(&self, t: u8) -> bool {
        self.counters.contains(&t)
    }

    /// Whether action `a`'s preconditions hold (docs/rules.md §4.1).
    fn is_legal(&self, a: u8) -> bool {
        let free_hand = self.hands_used() < HAND_CAPACITY;
        match a {
            WAIT => true,
            1..=6 => {
                let t = a;
                match self.tables[usize::from(t - 1)].status {
                    status::READY_TO_ORDER | status::DISHES => free_hand,
                    status::WAITING_FOR_FOOD => self.hands.contains(&food(t)),
                    status::WAITING_FOR_BILL => true,
                    _ => false,
                }
            }
            HAND_IN_ORDERS => self.hands.iter().any(|&i| (1..=6).contains(&i)),
            8..=13 => free_hand && self.counter_holds(a - FIRST_PICK_UP + 1),
            DROP_DISHES => self.hands.iter().any(|&i| i > 12),
            15..=56 => {
                let g = usize::from((a - FIRST_SEAT) / 6);
                let t = usize::from((a - FIRST_SEAT) % 6);
                g < usize::from(self.queue_len)
                    && self.tables[t].status == status::FREE
                    && self.queue[g].size <= TABLE_CAPACITIES[t]
            }
            _ => false,
        }
    }

    /// Bit `t` set: food of table `t` lies on a counter (bit 0: a counter slot is empty).
    fn food_on_counters(&self) -> u32 {
        // Counter slots hold 0..=6 (`check`), so the shift stays inside the word.
        self.counters
            .iter()
            .fold(0, |bits, &t| bits | 1u32.wrapping_shl(u32::from(t)))
    }

    /// The action mask of docs/rules.md §7: [`Self::is_legal`] for every action, computed in one
    /// pass (the server builds one per environment per step). Flags are combined with `&` and
    /// `|` rather than branches, and seating reads whole rows of a table: the states of unrelated
    /// environments follow no pattern a branch predictor could learn.
    pub fn action_mask(&self) -> ActionMask {
        let mut mask = [false; NUM_ACTIONS];
        self.write_action_mask(&mut mask);
        mask
    }

    /// [`Self::action_mask`] written into `out`, as any type a flag converts to: the server
    /// writes 0/1 bytes straight into its reply. (A mask returned and then copied is written
    /// byte by byte and read back in wide loads, which stall on the store buffer.)
    pub fn write_action_mask<T: From<bool> + Copy>(&self, out: &mut [T; NUM_ACTIONS]) {
        out.fill(T::from(false));
        let mask = out;
        let [first, second] = self.hands;
        // Hands fill in order, so a hand is free exactly when the last slot is empty.
        let free_hand = second == EMPTY;
        let is_order = |i: Item| (1..=6).contains(&i);
        mask[usize::from(WAIT)] = T::from(true);
        mask[usize::from(HAND_IN_ORDERS)] = T::from(is_order(first) | is_order(second));
        mask[usize::from(DROP_DISHES)] = T::from((first > 12) | (second > 12));
        let on_counters = self.food_on_counters();
        let mut free_tables = 0u8;
        for (i, table) in self.tables.iter().enumerate() {
            let t = i as u8 + 1;
            let s = table.status;
            let has_food = (first == food(t)) | (second == food(t));
            mask[usize::from(FIRST_GO_TO) + i] = T::from(
                ((s == status::READY_TO_ORDER) | (s == status::DISHES)) & free_hand
                    | (s == status::WAITING_FOR_FOOD) & has_food
                    | (s == status::WAITING_FOR_BILL),
            );
            mask[usize::from(FIRST_PICK_UP) + i] = T::from(free_hand & (on_counters >> t & 1 == 1));
            free_tables |= u8::from(s == status::FREE) << i;
        }
        if free_tables != 0 {
            for (g, group) in self.queue().iter().enumerate() {
                let fits = free_tables & FITS[usize::from(group.size)];
                let seats = &mut mask[usize::from(FIRST_SEAT) + NUM_TABLES * g..][..NUM_TABLES];
                for (seat, &fit) in seats.iter_mut().zip(&SPREAD[usize::from(fits)]) {
                    *seat = T::from(fit);
                }
            }
        }
    }

    /// Applies an action (docs/rules.md §4.1); with `SHAPED`, adds the expert's shaping.
    fn apply<const SHAPED: bool>(&mut self, a: u8) {
        if !self.is_legal(a) {
            return;
        }
        match a {
            WAIT => {}
            FIRST_GO_TO..=6 => self.go_to::<SHAPED>(a),
            HAND_IN_ORDERS => {
                for item in self.hands {
                    if (1..=6).contains(&item) {
                        self.score += 10;
                        self.place_order(item);
                    }
                }
                self.drop_from_hands(|i| (1..=6).contains(&i));
                self.score += 10;
            }
            8..=13 => {
                let t = a - FIRST_PICK_UP + 1;
                self.score += 10;
                if let Some(slot) = self.counters.iter_mut().find(|c| **c == t) {
                    *slot = 0;
                }
                self.hold(food(t));
                if SHAPED && let Some(group) = self.seated_group(usize::from(t)) {
                    self.score += shaped_bonus(group.patience, 10);
                }
            }
            DROP_DISHES => {
                let dishes = self.hands.iter().filter(|&&i| i > 12).count() as i64;
                self.score += 10 * dishes;
                self.drop_from_hands(|i| i > 12);
                self.score += 10;
            }
            _ => {
                let g = usize::from((a - FIRST_SEAT) / 6);
                let t = usize::from((a - FIRST_SEAT) % 6);
                let mut group = self.queue[g];
                self.queue.copy_within(g + 1.., g);
                self.queue_len -= 1;
                if SHAPED && group.size <= 4 && TABLE_CAPACITIES[t] == 6 {
                    self.score -= 100;
                }
                self.score += 10;
                group.buffer += 100;
                if SHAPED {
                    self.score += shaped_bonus(group.patience, 5);
                }
                self.tables[t] = Table {
                    status: status::READING,
                    group,
                    since: self.now,
                };
            }
        }
    }

    fn place_order(&mut self, t: u8) {
        let n = usize::from(self.orders_len);
        if n < ORDER_CAPACITY {
            self.orders[n] = Order {
                table: t,
                placed: self.now,
            };
            self.orders_len += 1;
        }
    }

    /// Actions 1..=6, whose preconditions have been checked.
    fn go_to<const SHAPED: bool>(&mut self, t: u8) {
        let now = self.now;
        let table = &mut self.tables[usize::from(t - 1)];
        let bonus = if SHAPED {
            shaped_bonus(table.group.patience, 10)
        } else {
            0
        };
        match table.status {
            status::READY_TO_ORDER => {
                table.status = status::WAITING_FOR_FOOD;
                table.group.buffer += 100;
                self.hold(order(t));
                self.score += 20 + bonus;
            }
            status::WAITING_FOR_FOOD => {
                table.status = status::EATING;
                table.group.buffer += 100;
                table.since = now;
                if let Some(pos) = self.hands.iter().position(|&i| i == food(t)) {
                    self.hands.copy_within(pos + 1.., pos);
                    self.hands[HAND_CAPACITY - 1] = EMPTY;
                }
                self.score += 30 + bonus;
            }
            status::WAITING_FOR_BILL => {
                table.status = status::DISHES;
                self.score += 50 + bonus;
            }
            _ => {
                // status::DISHES: the precondition held.
                table.status = status::FREE;
                self.hold(dish(t));
                self.score += 40;
            }
        }
    }

    /// One tick of time (docs/rules.md §5).
    fn advance(&mut self) {
        let config = self.config;
        // 1. The queue loses patience; groups at 0 leave without a penalty.
        let mut kept = 0;
        for i in 0..usize::from(self.queue_len) {
            let mut group = self.queue[i];
            if group.decay(&config) {
                self.lost += 1;
            } else {
                self.queue[kept] = group;
                kept += 1;
            }
        }
        self.queue_len = kept as u8;

        // 2. Seated groups lose patience; at 0 they run away. Every table's group is decayed and
        // only a seated one keeps the result: selects rather than a branch on the status, which
        // no predictor can guess across environments.
        for t in 1..=NUM_TABLES as u8 {
            let table = &mut self.tables[usize::from(t - 1)];
            let seated = table.is_seated();
            let mut group = table.group;
            let gone = group.decay(&config);
            table.group.patience = if seated {
                group.patience
            } else {
                table.group.patience
            };
            table.group.buffer = if seated {
                group.buffer
            } else {
                table.group.buffer
            };
            if seated && gone {
                *table = Table::default();
                self.run_away(t);
            }
        }

        // 3. The kitchen.
        let now = self.now;
        let mut kept = 0;
        for i in 0..usize::from(self.orders_len) {
            let o = self.orders[i];
            if now - o.placed < config.cooking_ticks {
                self.orders[kept] = o;
                kept += 1;
                continue;
            }
            if self.counter_holds(o.table) {
                // Quirk: this order and every later one are dropped.
                break;
            }
            // Quirk: with no empty slot the food is lost.
            if let Some(slot) = self.counters.iter_mut().find(|c| **c == 0) {
                *slot = o.table;
            }
        }
        self.orders_len = kept as u8;

        // 4. Reading and eating end (selects, as in 2.; `since` is only meaningful while
        // reading or eating, hence the wrapping difference).
        for table in &mut self.tables {
            let elapsed = now.wrapping_sub(table.since);
            let read = (table.status == status::READING) & (elapsed >= config.reading_ticks);
            let eaten = (table.status == status::EATING) & (elapsed >= config.eating_ticks);
            table.status = if read {
                status::READY_TO_ORDER
            } else if eaten {
                status::WAITING_FOR_BILL
            } else {
                table.status
            };
        }

        // 5. Arrivals.
        if now > self.next_arrival && usize::from(self.queue_len) < QUEUE_CAPACITY {
            self.arrive();
        }

        // 6.
        self.now += 1;
    }

    /// A group ran away from table `t`: its items, food and orders go too.
    fn run_away(&mut self, t: u8) {
        self.lost += 1;
        self.score -= 500;
        self.drop_from_hands(|i| table_of(i) == t);
        for c in &mut self.counters {
            if *c == t {
                *c = 0;
            }
        }
        let mut kept = 0;
        for i in 0..usize::from(self.orders_len) {
            if self.orders[i].table != t {
                self.orders[kept] = self.orders[i];
                kept += 1;
            }
        }
        self.orders_len = kept as u8;
    }

    /// The next group of the arrival list joins the queue (which has room).
    fn arrive(&mut self) {
        let entry = self.arrivals[(self.arrived % u32::from(self.arrivals_len)) as usize];
        self.queue[usize::from(self.queue_len)] =
            Group::arriving(entry >> 4, entry & 0x0f, &self.config);
        self.queue_len += 1;
        self.arrived += 1;
        self.next_arrival = self.now + self.config.arrival_interval;
    }

    /// The 40-number observation of docs/rules.md §6.
    pub fn observation(&self) -> Observation {
        let mut obs = [0i8; OBSERVATION_SIZE];
        self.write_observation(&mut obs, |v| v);
        obs
    }

    /// [`Self::observation`] written into `out`, each number through `to`: the server writes
    /// int8 bytes straight into its reply (see [`Self::write_action_mask`]).
    pub fn write_observation<T: Copy>(
        &self,
        out: &mut [T; OBSERVATION_SIZE],
        to: impl Fn(i8) -> T,
    ) {
        out.fill(to(0));
        let obs = out;
        for (t, table) in self.tables.iter().enumerate() {
            obs[3 * t] = to(table.status as i8);
            obs[3 * t + 1] = to(TABLE_CAPACITIES[t] as i8);
            // Computed for every table and selected, rather than a branch (see `action_mask`).
            let level = table.group.patience_level();
            obs[3 * t + 2] = to(if table.is_seated() { level } else { -1 });
        }
        let on_counters = self.food_on_counters();
        for t in 0..NUM_TABLES {
            obs[18 + t] = to((on_counters >> (t + 1) & 1) as i8);
        }
        for (g, group) in self.queue().iter().enumerate() {
            obs[24 + 2 * g] = to(group.patience_level());
            obs[25 + 2 * g] = to(group.size as i8);
        }
        obs[38] = to(self.hands[0] as i8);
        obs[39] = to(self.hands[1] as i8);
    }

    /// Checks what a deserialised state must satisfy so that no later step can misbehave and
    /// every observation stays inside [`super::observation_bounds`]: each field within what play
    /// can reach from a reset with this configuration.
    pub(crate) fn check(&self) -> Result<(), StateError> {
        let config = &self.config;
        config
            .validate()
            .map_err(|_| StateError("configuration out of range"))?;
        // Far below u32::MAX, so that no tick arithmetic of a restored game can overflow. (A
        // game may be stepped past its time limit, and past its last life, so neither bounds
        // the clock or the groups lost; sessions never do.)
        let clock_ok = self.now <= MAX_EPISODE_TICKS
            && self.next_arrival <= self.now + config.arrival_interval;
        if !clock_ok {
            return Err(StateError("clock"));
        }
        // One arrival at reset and at most one a tick; every group lost had arrived.
        if !(1..=self.now + 1).contains(&self.arrived) || self.lost > self.arrived {
            return Err(StateError("arrivals or groups lost"));
        }
        // A step gains at most 50 and loses at most 500 for each of the six tables.
        if self.score.unsigned_abs() > 4000 * u64::from(self.now) {
            return Err(StateError("score"));
        }
        if !(1..=MAX_ARRIVALS).contains(&usize::from(self.arrivals_len)) {
            return Err(StateError("arrival list length"));
        }
        let valid_group =
            |g: &Group| (1..=2).contains(&g.customer_type) && (1..=6).contains(&g.size);
        // Patience starts at its type's and only falls; a group at 0 is gone. The buffer starts
        // at 100 and gains 100 when seated, ordering and served: never above 400.
        let waiting = |g: &Group| {
            valid_group(g)
                && (1..=config.patience[usize::from(g.customer_type - 1)] as i32)
                    .contains(&g.patience)
                && (0..=400).contains(&g.buffer)
        };
        let arrivals_ok = self.arrivals().all(|(customer_type, size)| {
            valid_group(&Group {
                customer_type,
                size,
                ..Group::default()
            })
        });
        if !arrivals_ok {
            return Err(StateError("arrival list entry"));
        }
        if usize::from(self.queue_len) > QUEUE_CAPACITY || !self.queue().iter().all(waiting) {
            return Err(StateError("queue"));
        }
        for (t, table) in self.tables.iter().enumerate() {
            // A table that is not seated keeps its last group (or none) until the next seat.
            let group_ok = if table.is_seated() {
                waiting(&table.group) && table.group.size <= TABLE_CAPACITIES[t]
            } else {
                table.group == Group::default() || waiting(&table.group)
            };
            if table.status > 6 || !group_ok || table.since > self.now {
                return Err(StateError("table"));
            }
        }
        if self.counters.iter().any(|&c| usize::from(c) > NUM_TABLES) {
            return Err(StateError("counter"));
        }
        if self.hands.iter().any(|&i| i > 18) || (self.hands[0] == EMPTY && self.hands[1] != EMPTY)
        {
            return Err(StateError("hands"));
        }
        let orders = &self.orders[..usize::from(self.orders_len.min(ORDER_CAPACITY as u8))];
        if usize::from(self.orders_len) > ORDER_CAPACITY
            || orders
                .iter()
                .any(|o| !(1..=6).contains(&o.table) || o.placed > self.now)
        {
            return Err(StateError("orders"));
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn restaurant(arrivals: &[(u32, u32)]) -> Restaurant {
        let (packed, len) = pack_arrivals(arrivals).unwrap();
        Restaurant::new(Config::default(), packed, len)
    }

    #[test]
    fn action_mask_agrees_with_each_precondition() {
        let mut game = crate::sim::Game::new(Config::default()).unwrap();
        let mut checked = 0;
        for seed in 0..40u64 {
            game.reset(Some(seed), None).unwrap();
            let mut r = *game.restaurant();
            for i in 0..3000u32 {
                let mask = r.action_mask();
                for a in 0..NUM_ACTIONS as u8 {
                    assert_eq!(mask[usize::from(a)], r.is_legal(a), "action {a}");
                }
                checked += 1;
                // Mostly legal actions, chosen by a fixed scramble, so that play gets somewhere.
                let legal: Vec<u8> = (0..NUM_ACTIONS as u8)
                    .filter(|&a| mask[usize::from(a)])
                    .collect();
                let a = legal[(i as usize * 7 + seed as usize) % legal.len()];
                if r.step(a).terminated {
                    break;
                }
            }
        }
        assert!(checked > 4000);
    }

    #[test]
    fn half_even_rounding_like_cpython() {
        // round(0.5) = 0, round(1.5) = 2, round(2.5) = 2, round(0.6) = 1
        assert_eq!(shaped_bonus(695, 10), 0);
        assert_eq!(shaped_bonus(685, 10), 2);
        assert_eq!(shaped_bonus(675, 10), 2);
        assert_eq!(shaped_bonus(694, 10), 1);
        assert_eq!(shaped_bonus(700, 10), 0);
        assert_eq!(shaped_bonus(697, 5), 1);
        assert_eq!(shaped_bonus(698, 5), 0);
    }

    #[test]
    fn first_group_arrives_at_reset_then_every_nine_ticks() {
        let mut r = restaurant(&[(1, 2)]);
        assert_eq!(r.queue().len(), 1);
        let mut arrivals = vec![];
        for _ in 0..30 {
            let before = r.queue().len();
            let now = r.tick();
            r.step(WAIT);
            if r.queue().len() > before {
                arrivals.push(now);
            }
        }
        assert_eq!(arrivals, vec![9, 18, 27]);
    }

    #[test]
    fn size_must_fit_the_table() {
        let r = restaurant(&[(1, 6)]);
        let mask = r.action_mask();
        // group 1 at table 4 (capacity 6) only.
        let legal: Vec<usize> = (15..57).filter(|&a| mask[a]).collect();
        assert_eq!(legal, vec![15 + 3]);
    }

    #[test]
    fn run_away_costs_500_and_clears_the_table() {
        let mut r = restaurant(&[(1, 2)]);
        r.step(15); // seat at table 1
        let mut steps = 0;
        while r.table_status(1) != status::FREE {
            r.step(WAIT);
            steps += 1;
            assert!(steps < 1000);
        }
        assert_eq!(r.score(), 10 - 500);
        assert!(r.lost() >= 1);
    }
}
